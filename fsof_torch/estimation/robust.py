"""Robust kernels ρ of squared residual norms, and their IRLS weights.

For a squared residual norm r² and a scale c (in the residual's unit), with ρ'(0) = 1 so that
every kernel equals least squares for small residuals:

    l2       ρ = r²                               w = 1
    cauchy   ρ = c² log(1 + r²/c²)                w = 1 / (1 + r²/c²)
    soft_l1  ρ = 2 c² (sqrt(1 + r²/c²) - 1)       w = 1 / sqrt(1 + r²/c²)     (SciPy's)
    huber    ρ = r² (r <= c), c (2 r - c) else    w = min(1, c / r)
    tukey    ρ = c²/3 (1 - (1 - r²/c²)³) (r < c), c²/3 else    w = (1 - r²/c²)² (r < c), 0 else

w = dρ/d(r²) is the weight of iteratively reweighted least squares.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .._check import check_float_tensor, check_number, is_number, option_error, result_dtype, scalar, skip_values

__all__ = ["ROBUST_KERNELS", "robust_weight", "robust_cost", "robust_terms", "far_outlier_cost", "check_kernel",
           "check_scale", "check_fixed", "check_fit_options"]

ROBUST_KERNELS = ("cauchy", "huber", "soft_l1", "tukey", "l2")


def check_kernel(kind: object, name: str = "robust") -> str:
    """``kind``, a name of :data:`ROBUST_KERNELS`; the error names the caller's argument ``name``
    (the fits' ``robust``, the solver's ``kernel``, the kernels' ``kind``)."""
    if kind not in ROBUST_KERNELS:
        raise ValueError(f"{name}: expected one of {ROBUST_KERNELS}, got {kind!r}")
    return kind


def check_fixed(value: object, name: str) -> None:
    """A number read as a float (a kernel's ``scale``, the losses' ``gamma``) may not be a tensor
    that requires grad: its gradient would be lost, so a learnable one would silently never change."""
    if isinstance(value, Tensor) and value.requires_grad:
        raise TypeError(f"{name}: expected a fixed number, got a tensor that requires grad (read as a number, its "
                        f"gradient would be lost: a learnable {name} would never change)")


def check_fit_options(robust: str, scale: float, max_iter: int, tol: float, max_points: int | None,
                      inlier_threshold: float | None = None, min_points: int = 1,
                      min_inlier_fraction: float = 0.0) -> tuple[float, float, float | None, float]:
    """A robust fit's options (:func:`~fsof_torch.estimation.flow_fit.fit_road`'s, and the image
    fit's) checked: a TypeError or ValueError naming the first bad one. Returns ``scale``,
    ``tol``, ``inlier_threshold`` and ``min_inlier_fraction`` as Python numbers (a 0-d tensor
    read), for the fit to use."""
    check_kernel(robust)
    scale, tol, inlier_threshold, min_inlier_fraction, max_iter, max_points, min_points = (
        scalar(v, n) for n, v in (("scale", scale), ("tol", tol), ("inlier_threshold", inlier_threshold),
                                  ("min_inlier_fraction", min_inlier_fraction), ("max_iter", max_iter),
                                  ("max_points", max_points), ("min_points", min_points)))

    def positive(name: str, value: object, integer: bool = False, low: float = 0.0) -> None:
        if not is_number(value, integer=integer) or not math.isfinite(value) or not value > low:
            kind = "an int" if integer else "a finite number"
            raise option_error(value, f"{name}: expected {kind} > {low:g}, got {value!r}", integer=integer)

    positive("scale", scale)
    positive("max_iter", max_iter, integer=True)
    positive("tol", tol)
    if max_points is not None:
        positive("max_points", max_points, integer=True, low=15)
    if inlier_threshold is not None:
        positive("inlier_threshold", inlier_threshold)
    if not is_number(min_points, integer=True) or min_points < 1:
        raise option_error(min_points, f"min_points: expected an int >= 1, got {min_points!r}", integer=True)
    if not (is_number(min_inlier_fraction) and 0.0 <= min_inlier_fraction <= 1.0):
        raise option_error(min_inlier_fraction,
                           f"min_inlier_fraction: expected a number in [0, 1], got {min_inlier_fraction!r}")
    return (float(scale), float(tol), None if inlier_threshold is None else float(inlier_threshold),
            float(min_inlier_fraction))


def check_scale(scale: object) -> None:
    """``scale``: a finite number > 0, or a real tensor of them (one host read: the public
    functions and :func:`~fsof_torch.estimation.solver.solve`, once, check it; :func:`robust_terms`
    inside the solver's loop does not)."""
    if not isinstance(scale, Tensor):
        check_number(scale, "scale", positive=True)
        return
    if scale.dtype == torch.bool or scale.is_complex():
        raise TypeError(f"scale: expected a number or a real tensor, got dtype {scale.dtype}")
    if skip_values(scale):
        return
    good = torch.isfinite(scale) & (scale > 0)
    if not bool(good.all()):
        bad = scale[~good].flatten()[:3].tolist()
        raise ValueError(f"scale: expected finite values > 0, got {bad}")


def _checked_r2(r2: object) -> Tensor:
    """``r2``: a real float tensor of finite values >= 0 (one host read), lifted from half
    precision to float32 (r² / c² overflows float16 at a few hundred scales)."""
    check_float_tensor(r2, "r2")
    if not skip_values(r2) and r2.numel():
        lo, hi = torch.aminmax(r2.detach())
        if not bool(torch.isfinite(hi) & (lo >= 0)):  # (NaN fails both)
            bad = r2[~(torch.isfinite(r2) & (r2 >= 0))].flatten()[:3].tolist()
            raise ValueError(f"r2: expected finite squared norms >= 0, got {bad}")
    return r2.to(result_dtype(r2))


def _lifted(scale: Tensor | float) -> Tensor | float:
    return scale.to(result_dtype(scale)) if isinstance(scale, Tensor) and scale.is_floating_point() else scale


def robust_weight(r2: Tensor, scale: Tensor | float, kind: str = "cauchy") -> Tensor:
    """IRLS weight w = dρ/d(r²) for squared residual norms ``r2`` (a float tensor of any shape,
    finite and >= 0; ``scale``, a finite number > 0 or a tensor of them, broadcasts: the result
    has their broadcast shape, whatever the kernel). Computed and returned in at least float32
    (half precision lifted)."""
    check_kernel(kind, "kind")
    check_scale(scale)
    r2, scale = _checked_r2(r2), _lifted(scale)
    z = r2 / (scale * scale)
    return torch.ones_like(z) if kind == "l2" else _unit_kernel(z, kind, cost=False)[1]


def robust_cost(r2: Tensor, scale: Tensor | float, kind: str = "cauchy") -> Tensor:
    """ρ(r²), matching :func:`robust_weight` (its checks, shape and dtype)."""
    check_kernel(kind, "kind")
    check_scale(scale)
    r2, scale = _checked_r2(r2), _lifted(scale)
    c2 = scale * scale
    if kind == "l2":  # (ρ = r², broadcast with the scale: a result of its own, not the caller's tensor)
        return r2 * torch.ones_like(r2 / c2)
    return c2 * _unit_kernel(r2 / c2, kind, weight=False)[0]


def robust_terms(r2: Tensor, scale: Tensor, kind: str, mask: Tensor) -> tuple[Tensor, Tensor]:
    """Σ ρ(r²) over the points that count, and their IRLS weights, sharing the intermediate
    terms: the solver needs both at every evaluation. Unchecked (no host read inside the solver's
    loop): the caller owns its values and dtype.

    Args:
        r2: (B, N) squared residual norms (finite everywhere).
        scale: (B,) the kernel's scale, or (B, S): S scales at once.
        mask: (B, N) 1.0 where a point counts, 0.0 where not (a product with it is cheaper than a
            select).

    Returns:
        ``(cost (B,), weights (B, N))``, or (B, S) and (B, S, N) for S scales; the weights are 0
        where the mask is.
    """
    if scale.dim() == 2:
        r2, mask = r2.unsqueeze(1), mask.unsqueeze(1)
    if kind == "l2":
        return (r2 * mask).sum(-1).expand(scale.shape), mask.expand(*scale.shape, mask.shape[-1])
    c2 = scale * scale
    z = r2 / c2.unsqueeze(-1)
    if kind == "cauchy":  # (w = mask / (1 + z): the weight and its mask in one division, the same bits)
        w = torch.div(mask, z + 1.0)
        rho = z.log1p_()
    else:
        rho, w = _unit_kernel(z, kind, in_place=True)
        w = w.mul_(mask)
    # every kernel is ρ(r²) = c² ρ₁(r² / c²): the scale multiplies the sum, not each point
    return c2 * torch.linalg.vecdot(rho, mask), w


def _unit_kernel(z: Tensor, kind: str, cost: bool = True, weight: bool = True,
                 in_place: bool = False) -> tuple[Tensor | None, Tensor | None]:
    """(ρ₁(z), w(z)) of the table above at unit scale (z = r² / c²), each where asked for
    (``in_place``: z is the caller's scratch and may be overwritten)."""
    rho = w = None
    if kind == "cauchy":
        if weight:
            w = (1.0 + z).reciprocal_()
        if cost:
            rho = z.log1p_() if in_place else torch.log1p(z)
    elif kind == "soft_l1":
        root = torch.sqrt(1.0 + z)
        if weight:
            w = root.reciprocal()
        if cost:
            rho = 2.0 * (root - 1.0)
    elif kind == "huber":
        root = torch.sqrt(z.clamp_min(torch.finfo(z.dtype).tiny))
        inside = z <= 1.0
        if weight:
            w = torch.where(inside, 1.0, root.reciprocal())
        if cost:
            rho = torch.where(inside, z, 2.0 * root - 1.0)
    else:  # tukey: t = 1 - r²/c² inside the cut, 0 beyond
        t = (1.0 - z).clamp_min_(0.0)
        t2 = t * t
        if weight:
            w = t2
        if cost:
            rho = (1.0 - t2 * t) / 3.0
    return rho, w


# ρ₁(10⁴) per kernel, computed once at import (no host read inside a fit)
_FAR = {kind: float(robust_cost(torch.tensor(1e4, dtype=torch.float64, device="cpu"), 1.0, kind)) for kind in ROBUST_KERNELS}


def far_outlier_cost(kind: str) -> float:
    """ρ(10⁴ c²) / c²: the cost of a residual a hundred scales out at unit scale (every kernel is
    ρ(r²) = c² ρ₁(r² / c²)); the solver charges it for a point where the model is undefined."""
    return _FAR[check_kernel(kind, "kind")]
