"""One batched robust solver for every estimator of the library: Levenberg–Marquardt with a robust
kernel, Gaussian priors, bounds and per-sample convergence.

The problem (B independent samples, P parameters each, N residual points per sample) minimises

    E(p) = Σ_i ρ(r_i(p)²) + m · (n - n_used(p)) + Σ_k λ_k (p_k - μ_k)²

with ρ a robust kernel of scale c (:mod:`~fsof_torch.estimation.robust`), ``m`` the cost of a
point where the model is not defined (that of a far outlier, so that a fit cannot shrink the
model's domain to escape its residuals), and an optional Gaussian prior of mean μ and precision λ
(in residual² per parameter²). Each iteration solves the damped normal equations
(A + λ diag(A)) δ = -g by Cholesky (no host read), with A = Jᵀ W J + prior and g = Jᵀ W r the
IRLS normal equations (the problem builds them, knowing its structure), holding a parameter at
a bound that the step would push out of it (a simple active set: its row and column decoupled,
its gradient 0), clamps the candidate to the bounds and keeps it per sample where E went down;
else it damps more and retries the rejected step at half its length (E, which the step raised, is
least within its first half, where more damping alone barely shortens a step while the damping is
still small), or, a fresh step that moved points out of the problem's ``domain``, with the
parameters that move it held (:class:`Problem`). Each
candidate is evaluated once: its cost, its weights and its normal equations; a sample whose step
was rejected keeps those of its current point.

The kernel's scale can be annealed from the spread of the first residuals down to c (halving with
each accepted step, or dropping to the new residuals' spread), so that a wrong start is not
locked in by its own weights.

The loop runs a fixed budget of ``max_iter`` iterations with the convergence of each sample kept
on the device; converged samples stop moving. After ``check_every`` iterations, then after 1, 1, 2,
4, ... more (or after the iterations listed): one host read asks whether all have converged, to
stop early (``check_every=None``: never, for a GPU loop without synchronisation). The checks change
no result: they only end the loop. The first of them also tells the arguments' values (finite
start, prior and bounds), decided on the device before the loop.

The solver works in the start's dtype, half precision lifted to float32, with autocast off.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any, Callable, Protocol, Sequence

import torch
from torch import Tensor

from .._check import (autocast_off, check_float_tensor, check_int, check_number, check_shape, option_error,
                      result_dtype, scalar, skip_values)
from .linalg import positive_definite, spd_solve
from .robust import check_kernel, check_scale, far_outlier_cost, robust_terms

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
    Optionally ``domain``: (P,) bool, the parameters that move the points' domain (a flow fit's
    roll and pitch, which move the horizon), or None: with ``missing="outlier"`` a fresh step
    rejected because it moved points out of the domain is retried with those held, along its
    edge, the next such rejection at half its length (shortened along its own direction, the step
    lost the same points: a fit of a mask up to the horizon stalled there, short of its minimum).
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
        iterations: (B,) int64, iterations run while the sample was active (not yet converged):
            accepted steps and rejected (retried) ones alike.
        evaluation: the problem's :class:`Evaluation` at the estimate (its residuals and the
            points that count; not the problem's state).
        weights: (B, N) the final IRLS weights (0 where not used).
        normal: (B, P, P) JᵀWJ + prior at the estimate (fixed parameters: identity rows).
        scale: (B,) the kernel's final scale.
        free: (B, P) bool, the parameters estimated (None: all of them).
        prior: (B, P) the prior's precision λ in ``normal`` (None: no prior).
    """

    params: Tensor
    cost: Tensor
    converged: Tensor
    iterations: Tensor
    evaluation: Evaluation
    weights: Tensor
    normal: Tensor
    scale: Tensor
    free: Tensor | None = None
    prior: Tensor | None = None

    def conditioning(self) -> Tensor:
        """The smallest eigenvalue of the normal matrix scaled to a unit diagonal (B,): near 0
        when two parameters are nearly collinear for the data."""
        return torch.linalg.eigvalsh(_unit_diagonal(self.normal))[..., 0]

    def well_conditioned(self, margin: float = 1e-9) -> Tensor:
        """(B,) bool: :meth:`conditioning` exceeds ``margin`` (decided without a host read)."""
        return positive_definite(_unit_diagonal(self.normal), margin)

    def covariance(self, prior_noise: Tensor | float | None = None) -> Tensor:
        """(B, P, P) parameter covariance: the inverse normal matrix times the weighted residual
        variance σ² per degree of freedom (the points' weights minus the free parameters); 0 rows
        and columns for fixed parameters.

        With ``prior_noise`` ν ((B,) or a number: the residuals' standard deviation that the
        prior's precision λ was set against, λ = ν² / σ_p² for a prior of standard deviation σ_p),
        the posterior covariance (JᵀWJ / σ² + λ / ν²)⁻¹ instead: the prior keeps its own weight
        where the residuals' variance differs from ν² (without it, the prior's share is scaled
        with the data's, and a parameter that the data leave to the prior is reported as known
        to σ_p σ / ν). ν: a finite number > 0, or a real tensor of shape (), (1,) or (B,) (its
        values not read: no host read); else a TypeError or ValueError names ``prior_noise``. σ²
        is taken at least 1e4 ε ν² (ε the dtype's epsilon; σ / ν about 1.5e-6 in float64): with
        exact data a parameter that the data leave to its prior is still reported as known to
        σ_p (the prior's weight in the normal matrix, rounded, would otherwise swamp the data's
        and report +inf), and the others as known to about that fraction of ν.

        Where the
        problem is singular (an empty mask, one pixel, one row: the normal matrix's Cholesky
        fails, or its unit-diagonal form has no eigenvalue above 1e4 × the dtype's epsilon,
        about 2e-12 in float64, below which its inverse is rounding noise), or where no degree of
        freedom is left (the residuals' weight at most the free parameters: an exact fit says
        nothing of the noise), the free parameters' variances are +inf and the rest 0: nothing is
        known of them (never NaN)."""
        w, ev = self.weights, self.evaluation
        B, P = self.params.shape
        R = 1 if ev.residual is None else ev.residual.shape[1]
        # weights as fractional counts: a down-weighted outlier counts for its weight; the fixed
        # parameters took no degree of freedom
        n_free = P if self.free is None else self.free.expand(B, P).sum(1)
        dof = R * w.sum(1) - n_free
        exact = dof <= 0  # (no more residuals' weight than free parameters: the noise is unknown)
        dof = dof.clamp_min(1.0)
        sigma2 = (w * ev.r2).sum(1) / dof
        eye = torch.eye(P, dtype=self.normal.dtype, device=self.normal.device)
        A = self.normal
        if prior_noise is not None and self.prior is not None:
            # σ² (JᵀWJ + λ σ² / ν²)⁻¹ = (JᵀWJ / σ² + λ / ν²)⁻¹ (the fixed rows stay the identity's)
            nu2 = _checked_noise(prior_noise, B, A).square()
            # (A's prior rows hold JᵀWJ + λ, λ's rounding beyond JᵀWJ's share where the data barely see
            # the parameter: λ σ² / ν² must stay above it, or A is indefinite and the result +inf)
            sigma2 = torch.maximum(sigma2, nu2 * (1e4 * torch.finfo(A.dtype).eps))
            lam = self.prior.to(A.dtype) * (sigma2 / nu2 - 1.0).unsqueeze(-1)
            if self.free is not None:
                lam = torch.where(self.free.expand(B, P), lam, 0.0)
            A = A + torch.diag_embed(lam)
        cov = spd_solve(A, eye.expand_as(A)) * sigma2.reshape(-1, 1, 1)
        free = torch.ones(B, P, dtype=torch.bool, device=cov.device) if self.free is None else self.free.expand(B, P)
        both = free.unsqueeze(-1) & free.unsqueeze(-2)
        cov = torch.where(both, cov, 0.0)
        # a Cholesky that fails leaves finite garbage in the solve: its status and the
        # unit-diagonal matrix's smallest eigenvalue decide, not the finiteness of the result
        margin = 1e4 * torch.finfo(A.dtype).eps
        singular = (~torch.isfinite(cov).flatten(1).all(1) | ~positive_definite(A)
                    | ~positive_definite(_unit_diagonal(A), margin) | exact)
        unknown = torch.diag_embed(torch.where(free, math.inf, 0.0).to(cov.dtype))
        return torch.where(singular.reshape(B, 1, 1), unknown, cov)


def _checked_noise(noise: object, B: int, like: Tensor) -> Tensor:
    """:meth:`Solution.covariance`'s ``prior_noise`` as (B,) in ``like``'s dtype and device: a
    finite number > 0 (checked), or a real tensor of shape (), (1,) or (B,) (its values not read)."""
    if not isinstance(noise, Tensor):
        return torch.full((B,), check_number(noise, "prior_noise", positive=True), dtype=like.dtype, device=like.device)
    if noise.dtype == torch.bool or noise.is_complex():
        raise TypeError(f"prior_noise: expected a number or a real tensor, got dtype {noise.dtype}")
    if noise.dim() > 1 or noise.numel() not in (1, B):
        raise ValueError(f"prior_noise: expected a number or a tensor of shape (), (1,) or ({B},), got shape "
                         f"{tuple(noise.shape)}")
    return noise.to(dtype=like.dtype, device=like.device).reshape(-1).expand(B)


def _checked_scale(scale: object, B: int, dt: torch.dtype, dev: torch.device, computed: bool) -> Tensor:
    """A tensor scale (or a scale function's result) as (B,). A given tensor is checked finite and
    > 0 (one host read: NaN, 0 or a negative scale would give a NaN cost that the loop takes for
    convergence); a function's result only for its shape (no host read: the function, such as the
    image fit's scale from the residuals, owns its values)."""
    what = "scale: expected the function to return" if computed else "scale: expected"
    try:
        s = torch.as_tensor(scale, dtype=dt, device=dev)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(f"{what} a float or a (B,) tensor, got {type(scale).__name__}") from None
    if s.dim() > 1 or s.numel() not in (1, B):
        raise ValueError(f"{what} a float or a ({B},) tensor (B of params), got shape {tuple(s.shape)}")
    s = s.reshape(-1).expand(B).clone()
    if not computed:
        check_scale(s)  # (robust.py's check of a scale: finite values > 0, one host read)
    return s


def _broadcasts_to(shape: torch.Size, B: int, P: int) -> bool:
    """``shape`` broadcasts to (B, P) (torch.broadcast_shapes written out: that is a Python
    reference implementation of about 10 µs a call, and each fit level checks four arguments)."""
    if len(shape) == 2:
        return shape[0] in (1, B) and shape[1] in (1, P)
    return len(shape) == 0 or (len(shape) == 1 and shape[0] in (1, P))


def _expand(x: Tensor | float | None, name: str, B: int, P: int, like: Tensor, fill: float) -> Tensor:
    """A per-parameter argument (a number, (P,) or (B, P), or anything that broadcasts to (B, P))
    as (B, P) of ``like``'s dtype and device; its type and shape checked (no host read)."""
    if x is None:
        return torch.full((B, P), fill, dtype=like.dtype, device=like.device)
    if isinstance(x, Tensor) and (x.dtype == torch.bool or x.is_complex()):
        raise TypeError(f"{name}: expected a number or a real tensor of shape ({P},) or ({B}, {P}), got dtype {x.dtype}")
    try:
        t = torch.as_tensor(x, dtype=like.dtype, device=like.device)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(f"{name}: expected a number or a tensor of shape ({P},) or ({B}, {P}), "
                        f"got {type(x).__name__}") from None
    if not _broadcasts_to(t.shape, B, P):
        raise ValueError(f"{name}: expected a number or shape ({P},) or ({B}, {P}) (B, P of params), "
                         f"got {tuple(t.shape)}")
    return t.expand(B, P)


def _check_free(free: object, B: int, P: int, dev: torch.device) -> Tensor:
    """``free`` as (B, P) bool (no host read)."""
    if not isinstance(free, Tensor) or free.dtype != torch.bool:
        got = f"dtype {free.dtype}" if isinstance(free, Tensor) else type(free).__name__
        raise TypeError(f"free: expected a bool tensor of shape ({P},) or ({B}, {P}), got {got}")
    if not _broadcasts_to(free.shape, B, P):
        raise ValueError(f"free: expected shape ({P},) or ({B}, {P}) (B, P of params), got {tuple(free.shape)}")
    return free.to(dev).expand(B, P)


def _values_hold(values: dict[str, Tensor | None]) -> Tensor:
    """0-d bool on the device: the given arguments' values hold (decided without a host read: the
    loop's first host read carries it, and :func:`_raise_bad_value` then names the first that
    fails). The bounds in one comparison: lower < +inf, upper > -inf and lower <= upper, none
    NaN, exactly where max(lower, -big) <= min(upper, big), big the dtype's largest number."""
    params, mu, lam, lo, hi = (values.get(k) for k in ("params", "prior_mean", "prior_precision", "lower", "upper"))
    held = torch.isfinite(params).all()
    if mu is not None:
        held = held & torch.isfinite(mu).all()
    if lam is not None:
        held = held & (torch.isfinite(lam) & (lam >= 0)).all()
    if lo is not None:
        big = torch.finfo(lo.dtype).max
        held = held & (lo.clamp_min(-big) <= hi.clamp_max(big)).all()
    return held


def _raise_bad_value(values: dict[str, Tensor | None]) -> None:
    """The error for the first argument whose values fail their check (host reads: the error
    path only)."""
    def some(x: Tensor, bad: Tensor) -> list:
        return x[bad].flatten()[:3].tolist()

    expected = {"params": ("finite start values", torch.isfinite), "prior_mean": ("finite values", torch.isfinite),
                "prior_precision": ("finite values >= 0", lambda x: torch.isfinite(x) & (x >= 0)),
                "lower": ("values below +inf (not NaN)", lambda x: x < math.inf),
                "upper": ("values above -inf (not NaN)", lambda x: x > -math.inf)}
    for name, (what, good) in expected.items():
        x = values.get(name)
        if x is not None and not bool(good(x).all()):
            raise ValueError(f"{name}: expected {what}, got {some(x, ~good(x))}")
    lo, hi = values["lower"], values["upper"]
    raise ValueError(f"lower, upper: expected lower <= upper, got lower {some(lo, lo > hi)} "
                     f"above upper {some(hi, lo > hi)}")


def _check_schedule(check_every: int | Sequence[int] | None, max_iter: int) -> list[int]:
    """The iterations after which :func:`solve` asks whether all samples converged: an int k gives
    k, then 1, 1, 2, 4, ... more (a stage that has not converged when expected usually needs one or
    two more iterations: each of those is checked, and then the gaps double)."""
    check_every = scalar(check_every, "check_every")  # (a 0-d integer tensor as its int)
    if check_every is None:
        return []
    if isinstance(check_every, numbers.Integral) and not isinstance(check_every, bool):
        if check_every < 1:
            raise ValueError(f"check_every: expected an int >= 1, a sequence of them or None, got {check_every!r}")
        out, gap = [int(check_every)], 1
        while out[-1] + gap < max_iter:
            out.append(out[-1] + gap)
            if len(out) > 2:  # the gaps: 1, 1, then doubling
                gap *= 2
        return [k for k in out if k < max_iter]
    try:  # (a rising range is sorted already)
        out = (list(check_every) if isinstance(check_every, range) and check_every.step > 0
               else sorted({int(k) for k in check_every}))
    except (TypeError, ValueError):  # (not a sequence, or of values int() refuses: a wrong type)
        raise TypeError(f"check_every: expected an int >= 1, a sequence of them or None, got {check_every!r}") from None
    if out and out[0] < 1:
        raise ValueError(f"check_every: expected iterations >= 1, got {check_every!r}")
    return [k for k in out if k < max_iter]


def solve(problem: Problem, params: Tensor, *, free: Tensor | None = None,
          prior_mean: Tensor | None = None, prior_precision: Tensor | Callable[[Tensor], Tensor] | None = None,
          lower: Tensor | None = None, upper: Tensor | None = None, kernel: str = "cauchy",
          scale: Tensor | float | Callable[[Evaluation], Tensor] = 1.0, anneal: bool = False, max_iter: int = 50,
          tol: float = 1e-6, resolution: float = 0.0, check_every: int | Sequence[int] | None = 2,
          damping: float = 1e-4, missing: str = "outlier", predict: bool = False) -> Solution:
    """Robust Levenberg–Marquardt for B independent samples (see the module docstring).

    Args:
        problem: a :class:`Problem`.
        params: (B, P) float, the start, finite (B, P >= 1; float64 recommended). The solver works
            in its dtype, half precision lifted to float32, with autocast off (the normal
            equations in bfloat16 would lose the fit), and returns the :class:`Solution` in it
            (in the problem's, where its residuals come in a wider dtype).
        free: (P,) or (B, P) bool, the parameters to estimate (default all); the others stay.
        prior_mean, prior_precision: (P,) or (B, P): a Gaussian prior λ (p - μ)² per parameter
            (precision 0: none); the mean finite (0 where not given), the precision finite and >= 0;
            the precision may be a function of the scale (B,) returning it (a prior whose weight
            follows the residuals' noise; its result is not read). A mean without a precision is a
            ValueError (it would weigh nothing).
        lower, upper: (P,) or (B, P) bounds (±inf: none; lower <= upper, no NaN); the start is
            clamped into them. A parameter at a bound that the step would push out of it is held
            there for that step (a simple active set), so that the others still reach the
            constrained minimum.
        kernel: a name of :data:`~fsof_torch.estimation.robust.ROBUST_KERNELS`.
        scale: the kernel's scale c (float or (B,)), in the residual's unit, or a function of the
            start's :class:`Evaluation` returning it (B,) (a scale from the residuals, without
            evaluating the start twice); finite and > 0 (a given tensor is checked by one host
            read before the loop; a function must return such values: its result is not read).
        anneal: start the scale at max(c, 3 · median residual norm), then with every accepted
            step halve it or drop it to 3 × the new residuals' median, whichever is smaller, down
            to c (a rejected step is retried, at half its length, at the same scale).
        max_iter: the iteration budget (an int >= 0).
        tol: converged when a step changes no parameter by more than tol (1 + |p|), or E by less
            than tol E (finite, >= 0).
        resolution: also converged when a step (accepted or not) moves the residuals by at most
            this fraction of their robust RMS (below what the points can resolve), or a rejected
            step by at most twice that (the cost, which it raised, is least within its first
            half); 0: off.
        predict: with ``resolution``, also converged after an accepted step when the next step,
            predicted from the normal equations there, would move the weighted residuals by at
            most that fraction (the Gauss–Newton prediction δᵀ A δ): a stage then ends without
            spending an evaluation on a step that would not matter. The answer differs from the
            unpredicted one by about that skipped step; a zero-residual problem is unaffected
            (the step predicted there removes the whole residual).
        check_every: stop early when all samples converged, checked (one host read each) after
            this many iterations, then after 1, 1, 2, 4, ... more: a handful of reads for any
            budget; or the iterations after which to check (a sequence); None: always run
            ``max_iter``. The values of ``params``, ``prior_mean``, ``prior_precision`` (a tensor),
            ``lower`` and ``upper`` are checked by the first of these reads (or by one after the
            loop where it makes none): a ValueError names the first bad one. With None nothing is
            read, and their values are the caller's to vouch for (their types and shapes are
            always checked).
        damping: the initial Levenberg–Marquardt damping (> 0).
        missing: what a point that does not count (not ``use``) costs: ``"outlier"``, as much as a
            far outlier (a flow fit must not shrink the model's domain to escape its residuals);
            ``"mean"``, the mean cost of the points that count (an image fit, whose points may
            rightly move out of the image), and where none counts, what they would all cost as
            far outliers.

    Returns:
        :class:`Solution`.
    """
    check_kernel(kernel, "kernel")
    if missing not in ("outlier", "mean"):
        raise ValueError(f"missing: expected 'outlier' or 'mean', got {missing!r}")
    max_iter = check_int(max_iter, "max_iter", minimum=0)
    tol = check_number(tol, "tol", nonnegative=True)
    resolution = check_number(resolution, "resolution", nonnegative=True)
    damping = check_number(damping, "damping", positive=True)
    checks = _check_schedule(check_every, max_iter)
    check_float_tensor(params, "params")
    check_shape(params, "params", ("B", "P"), nonempty=("B", "P"))
    if prior_mean is not None and prior_precision is None:  # (the prior is its precision's: it was left out unsaid)
        raise ValueError("prior_mean: given without prior_precision, it would weigh nothing: give the prior's "
                         "precision too (0 for a parameter without a prior)")
    if isinstance(scale, bool) or (isinstance(scale, (int, float)) and not (math.isfinite(scale) and scale > 0)):
        raise option_error(scale, f"scale: expected a finite number > 0, got {scale!r}")
    # (the problem's linear algebra too: autocast would build the normal equations in 16 bits)
    with autocast_off(params):
        # (a copy: with no accepted step, or max_iter=0, the result is not the caller's tensor)
        return _solve(problem, params.to(result_dtype(params), copy=True), free, prior_mean, prior_precision, lower, upper,
                      kernel, scale, anneal, max_iter, tol, resolution, checks, damping, missing, predict,
                      check_values=check_every is not None and not skip_values(params))


def _solve(problem: Problem, params: Tensor, free: Tensor | None, prior_mean: Tensor | None,
           prior_precision: Tensor | Callable[[Tensor], Tensor] | None, lower: Tensor | None,
           upper: Tensor | None, kernel: str, scale: Tensor | float | Callable[[Evaluation], Tensor],
           anneal: bool, max_iter: int, tol: float, resolution: float, checks: list[int], damping: float,
           missing: str, predict: bool, check_values: bool) -> Solution:
    """:func:`solve`'s loop, its scalar arguments checked, ``params`` in the working dtype."""
    B, P = params.shape
    dt, dev = params.dtype, params.device
    # optional parts cost nothing when absent (Python flags, not tensor tests)
    has_fixed = free is not None
    if has_fixed:
        fixed = ~_check_free(free, B, P, dev)
        fixed_rc = fixed.unsqueeze(-1) | fixed.unsqueeze(-2)
        eye_fixed = torch.eye(P, dtype=dt, device=dev) * fixed.unsqueeze(-1)
    has_bounds = lower is not None or upper is not None
    off_diagonal = ~torch.eye(P, dtype=torch.bool, device=dev)
    # the parameters that move the points' domain, held in some retries (see the loop)
    domain = getattr(problem, "domain", None) if missing == "outlier" else None
    if has_bounds:
        lo = _expand(lower, "lower", B, P, params, -float("inf"))
        hi = _expand(upper, "upper", B, P, params, float("inf"))
    has_prior = prior_precision is not None
    mu = None if prior_mean is None else _expand(prior_mean, "prior_mean", B, P, params, 0.0)
    lam_given = (None if prior_precision is None or callable(prior_precision)
                 else _expand(prior_precision, "prior_precision", B, P, params, 0.0))
    # the arguments' values, decided on the device; the loop's first host read tells them
    pending = None
    if check_values:
        values = {"params": params, "prior_mean": mu, "prior_precision": lam_given}
        if has_bounds:
            values.update(lower=lo, upper=hi)
        pending = _values_hold(values)

    if has_bounds:
        params = torch.minimum(torch.maximum(params, lo), hi)
    n = problem.count.to(dt).clamp_min(1)
    far = far_outlier_cost(kernel)
    # the loop's numbers as 0-d tensors of the working dtype: a Python number is wrapped into a
    # tensor at every op that takes it (about 0.6 µs each, 1 µs in a where). Only where the other
    # operand is in the working dtype, or the number is exact in it (the costs and normal equations
    # may come in a wider dtype: a number rounded to the working one would change them), and not
    # in divisions (one by a Python number may be computed as a product by its reciprocal, CUDA's).
    zero, half, one, four, eight, k_tol, k_lam_small, k_lam_stuck = torch.tensor(
        [0.0, 0.5, 1.0, 4.0, 8.0, tol, 1e-2, 1e8], dtype=dt, device=dev).unbind()
    res2 = resolution ** 2

    def evaluate(p: Tensor) -> Evaluation:
        """The problem at p, its residuals in at least the working dtype."""
        ev = problem.evaluate(p)
        if ev.r2.dtype != dt and torch.promote_types(ev.r2.dtype, dt) != ev.r2.dtype:
            ev = Evaluation(ev.r2.to(dt), ev.use, None if ev.residual is None else ev.residual.to(dt), ev.state)
        return ev

    def cost_and_weights(r2: Tensor, mask: Tensor, used: Tensor, d: Tensor | None, s: Tensor) -> tuple[Tensor, Tensor]:
        """E / n (B,) and the IRLS weights (B, N) at the scale s (B,); ``mask``: 1.0 where a point
        counts (B, N), ``used`` their number (B,); ``d``: the parameters' offset from the prior's
        mean. With s (B, S): E / n (B, S) and the weights (B, S, N) at S scales at once."""
        rho, w = robust_terms(r2, s, kernel, mask)
        nn, used = (n, used) if s.dim() == 1 else (n.unsqueeze(-1), used.unsqueeze(-1))
        # (a fixed scale's far-outlier cost is computed once)
        s_far = s * s * far if anneal else s_far_fixed
        if missing == "outlier":
            rho = torch.addcmul(rho, s_far, nn - used)
        else:
            # where no point counts, they all cost what far outliers would (not 0: a step that
            # moved every point out of view would be the best fit)
            rho = torch.where(used > zero, rho * (nn / used), s_far * nn if anneal else s_far_n)  # (used = 0: not read)
        if has_prior:
            prior = (lam_p * d.square()).sum(1)
            rho = rho + (prior if s.dim() == 1 else prior.unsqueeze(-1))
        return rho / nn, w

    def normal(ev: Evaluation, w: Tensor, d: Tensor | None) -> tuple[Tensor, Tensor]:
        A, g = problem.normal_equations(ev, w)
        if A.dtype != dt or g.dtype != dt:
            A, g = A.to(torch.promote_types(A.dtype, dt)), g.to(torch.promote_types(g.dtype, dt))
        if has_prior:
            A = A + lam_diag
            g = g + lam_p * d
        if has_fixed:
            A, g = torch.where(fixed_rc, eye_fixed, A), torch.where(fixed, zero, g)
        return A, g

    def damped_step(A: Tensor, g: Tensor, lam: Tensor, p: Tensor, held: Tensor | None = None) -> Tensor:
        """The step from p; a parameter at a bound that the descent direction -g points out of
        is held there (its row and column decoupled, its diagonal kept for the damping's scale,
        its gradient 0), so that the step is the other parameters' constrained one, not an
        unconstrained one that the clamp then cuts short; so are the parameters ``held``."""
        hold = held
        if has_bounds:
            hold = ((p <= lo) & (g > zero)) | ((p >= hi) & (g < zero)) | (False if held is None else held)
        if hold is not None:
            A = torch.where((hold.unsqueeze(-1) | hold.unsqueeze(-2)) & off_diagonal, zero, A)
            g = torch.where(hold, zero, g)
        return _damped_step(A, g, lam)

    def kernel_spread(ev: Evaluation) -> Tensor:
        """3 × the median residual norm (B,): the scale that keeps most points in the kernel."""
        if ev.r2.shape[1] == 0:  # (no points: no spread)
            return torch.zeros(B, dtype=dt, device=dev)
        med = torch.nanmedian(torch.where(ev.use, ev.r2, float("nan")), dim=1).values
        return 3.0 * torch.nan_to_num(med, nan=0.0).sqrt()

    def resolved(wr2: Tensor, w: Tensor, used: Tensor) -> Tensor:
        """What a step must move the squared residuals by, summed over the points that count, to
        matter (B,): resolution² × their robust mean square (``wr2``: Σ w r², B) × their number."""
        return res2 * wr2 / w.sum(1).clamp_min(1e-300) * used

    def counted(ev: Evaluation) -> tuple[Tensor, Tensor]:
        """The points that count as a 0/1 mask (B, N) in the residuals' dtype (the working one, or
        the problem's where it is wider), and their number."""
        # (bool's bytes read as uint8: the same 0/1 values, converted several times faster)
        mask = (ev.use.view(torch.uint8) if ev.use.dtype == torch.bool else ev.use).to(ev.r2.dtype)
        return mask, mask.sum(1)

    ev = evaluate(params)
    s_min = (torch.full((B,), float(scale), dtype=dt, device=dev) if isinstance(scale, (int, float))
             else _checked_scale(scale(ev) if callable(scale) else scale, B, dt, dev, callable(scale)))
    if has_prior:
        if mu is None:
            mu = _expand(None, "prior_mean", B, P, params, 0.0)
        lam_p = (_expand(prior_precision(s_min), "prior_precision", B, P, params, 0.0) if lam_given is None
                 else lam_given)
        lam_diag = torch.diag_embed(lam_p)  # (constant: built once, added to every normal matrix)
    if anneal:
        s = torch.maximum(s_min, kernel_spread(ev))
        s_top = s_min * (1 + 1e-12)  # (at the final scale, within rounding)
    else:
        s = s_min
        s_far_fixed = s * s * far
        s_far_n = s_far_fixed * n
    mask, used = counted(ev)
    d = params - mu if has_prior else None
    c, w = cost_and_weights(ev.r2, mask, used, d, s)
    A, g = normal(ev, w, d)
    if resolution > 0:
        bar = resolved(torch.linalg.vecdot(w, ev.r2), w, used)
    # the current point's residuals and weights (the points that count: ``mask``)
    r2, residual = ev.r2, ev.residual
    lam = torch.full((B,), damping, dtype=dt, device=dev)
    done = torch.zeros(B, dtype=torch.bool, device=dev)
    iters = torch.zeros(B, dtype=torch.long, device=dev)
    step = damped_step(A, g, lam, params)
    if domain is not None:  # (per sample: the step is a fresh one, not a retry; one along the domain's edge)
        fresh, edge = torch.ones(B, dtype=torch.bool, device=dev), torch.zeros(B, dtype=torch.bool, device=dev)
    for it in range(max_iter):
        active = ~done
        # no step for finished samples, and none from a singular system
        delta = torch.where(active.unsqueeze(-1), step, zero)
        cand = params + delta
        if has_bounds:
            cand = torch.minimum(torch.maximum(cand, lo), hi)
            delta = cand - params
        ev_c = evaluate(cand)
        mask_c, used_c = counted(ev_c)
        d_c = cand - mu if has_prior else None
        if anneal:
            # the scale an accepted step carries on with: halved, or the new residuals' spread;
            # the cost at the current scale decides, the weights are those at the next
            at_scale = s <= s_top
            s_c = torch.where(at_scale, s, torch.maximum(s_min, torch.minimum(half * s, kernel_spread(ev_c))))
            costs, w_c = cost_and_weights(ev_c.r2, mask_c, used_c, d_c, torch.stack([s, s_c], dim=-1))
            (c1, c_next), w_c = costs.unbind(1), w_c[:, 1]
        else:
            c1, w_c = cost_and_weights(ev_c.r2, mask_c, used_c, d_c, s)
        ok = (c1 <= c) & active  # (False for a NaN cost)
        rejected = ~ok  # (or finished: then its step is never taken)
        # converged: after an accepted step, E changed by less than tol E or no parameter by more
        # than tol (1 + |p|); after a rejected one, no parameter at small damping
        tiny = (delta.abs() <= k_tol * (one + cand.abs())).all(-1)
        small_ok = (c1 >= c * (1.0 - tol)) | tiny
        small_rejected = tiny & (lam <= k_lam_small)
        if resolution > 0:
            # the step moved the residuals (RMS) by at most ``resolution`` of their robust RMS
            # (also a rejected step: below resolution the cost cannot reliably go down any more)
            if residual is not None:
                moved = (ev_c.residual - residual).square_()
                moved = moved.squeeze(1) if moved.shape[1] == 1 else moved.sum(1)
            else:
                moved = (ev_c.r2.sqrt() - r2.sqrt()).square_()
            # (a finished sample does not move: it stays finished). A rejected step raised the
            # cost: about quadratic along the step, it is least within the step's first half,
            # which moves the residuals by at most a quarter of its squared move; where that is
            # within the resolution, more damped retries cannot move them by more (and a move
            # within bar is within 4 bar: bar >= 0)
            moved = torch.linalg.vecdot(moved, mask)
            small_ok = small_ok | (moved <= bar)
            small_rejected = small_rejected | (moved <= four * bar)
        # the candidate's normal equations; a rejected sample keeps its own (same point, same scale)
        A_c, g_c = normal(ev_c, w_c, d_c)
        keep = ok.unsqueeze(-1)
        keep3 = keep.unsqueeze(-1)
        params = torch.where(keep, cand, params)
        A, g = torch.where(keep3, A_c, A), torch.where(keep, g_c, g)
        w, mask, r2 = torch.where(keep, w_c, w), torch.where(keep, mask_c, mask), torch.where(keep, ev_c.r2, r2)
        if residual is not None:
            residual = torch.where(keep3, ev_c.residual, residual)
        if resolution > 0 or predict:
            wr2_c = torch.linalg.vecdot(w_c, ev_c.r2)  # (Σ w r² where the step was taken)
        if resolution > 0:
            bar = torch.where(ok, resolved(wr2_c, w_c, used_c), bar)
        c = torch.where(ok, c_next if anneal else c1, c)
        if domain is not None:
            lost = rejected & active & (used_c < used)
            used = torch.where(ok, used_c, used)
        iters += active
        lam = torch.where(ok, (lam / 3.0).clamp_min(1e-12), lam * eight)
        # the next step: a rejected one retried at half its length (see the module docstring),
        # else the damped step from the normal equations at the (new) point
        step = torch.where(rejected.unsqueeze(-1), half * delta, damped_step(A, g, lam, params))
        if domain is not None:
            # a step that moved points out of the domain (each then costs a far outlier: a flow
            # fit's horizon lifted over the mask's topmost pixels), shortened along its own
            # direction, loses the same points, and the fit ended at the domain's edge short of its
            # minimum: a fresh step's rejection is retried along the edge, the parameters that move
            # the domain held; the next such rejection at half its length (a wall worth crossing
            # is still crossed)
            along = lost & fresh
            step = torch.where(along.unsqueeze(-1), damped_step(A, g, lam, params, domain), step)
            fresh = torch.where(ok, ~edge, fresh & ~lost)
            edge = torch.where(ok, False, along)
        if predict:
            # the step predicted there: δᵀ A δ is what it would move the weighted squared
            # residuals by (to first order); below resolution² of their weighted sum it is not
            # worth an evaluation (after an accepted step; at the final scale, where annealing)
            moves = torch.linalg.vecdot(step, torch.bmm(A, step.unsqueeze(-1)).squeeze(-1))
            settled = moves <= res2 * wr2_c
            if not anneal:
                small_ok = small_ok | settled
        # (or stuck: rejected at a damping where no step moves any more)
        converged = torch.where(ok, small_ok, small_rejected | (lam > k_lam_stuck))
        if anneal:
            s = torch.where(ok, s_c, s)
            done = done | (at_scale & converged)
            if predict:
                done = done | (ok & settled & (s <= s_top))
        else:
            done = done | converged
        if checks and it + 1 == checks[0]:
            checks.pop(0)
            if pending is not None:  # (one host read: the arguments' values and convergence)
                held, all_done = divmod(int(2 * pending + done.all()), 2)  # (both in one int: one read)
                pending = None
                if not held:
                    _raise_bad_value(values)
                if all_done:
                    break
            elif bool(done.all()):
                break
    if pending is not None and not bool(pending):  # (the loop made no host read)
        _raise_bad_value(values)
    # (the problem's state is not kept: the normal equations built from it are)
    return Solution(params, c, done, iters, Evaluation(r2, mask > 0, residual), w, A, s, ~fixed if has_fixed else None,
                    lam_p if has_prior else None)


def _damped_step(A: Tensor, g: Tensor, lam: Tensor) -> Tensor:
    """The Levenberg–Marquardt step δ (B, P) of (A + λ diag(A)) δ = -g (Marquardt's scaling: the
    step does not depend on the parameters' units), 0 where the system is singular.

    The diagonal has a relative floor: a direction the data do not see must not be blown up to
    unit size.
    """
    d = A.diagonal(dim1=-2, dim2=-1)
    d = torch.maximum(d, 1e-12 * d.amax(-1, keepdim=True))
    step = spd_solve(A + torch.diag_embed(lam.unsqueeze(-1) * d), g.unsqueeze(-1))
    return step.squeeze(-1).neg_().nan_to_num_(0.0, 0.0, 0.0)


def _unit_diagonal(A: Tensor) -> Tensor:
    d = A.diagonal(dim1=-2, dim2=-1).clamp_min(torch.finfo(A.dtype).tiny).sqrt()
    return A / (d.unsqueeze(-1) * d.unsqueeze(-2))
