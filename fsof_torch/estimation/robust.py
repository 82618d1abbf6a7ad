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

import torch
from torch import Tensor

__all__ = ["ROBUST_KERNELS", "robust_weight", "robust_cost", "check_kernel"]

ROBUST_KERNELS = ("cauchy", "huber", "soft_l1", "tukey", "l2")


def check_kernel(kind: object) -> str:
    if kind not in ROBUST_KERNELS:
        raise ValueError(f"robust: expected one of {ROBUST_KERNELS}, got {kind!r}")
    return kind


def robust_weight(r2: Tensor, scale: Tensor | float, kind: str = "cauchy") -> Tensor:
    """IRLS weight w = dρ/d(r²) for squared residual norms ``r2`` (any shape; ``scale`` broadcasts)."""
    check_kernel(kind)
    if kind == "l2":
        return torch.ones_like(r2)
    z = r2 / (scale * scale)
    if kind == "cauchy":
        return 1.0 / (1.0 + z)
    if kind == "soft_l1":
        return torch.rsqrt(1.0 + z)
    if kind == "huber":
        return torch.where(z <= 1.0, 1.0, torch.rsqrt(z.clamp_min(torch.finfo(z.dtype).tiny)))
    return torch.where(z < 1.0, (1.0 - z) ** 2, 0.0)


def robust_cost(r2: Tensor, scale: Tensor | float, kind: str = "cauchy") -> Tensor:
    """ρ(r²) (same shape as ``r2``), matching :func:`robust_weight`."""
    check_kernel(kind)
    if kind == "l2":
        return r2
    c2 = scale * scale
    z = r2 / c2
    if kind == "cauchy":
        return c2 * torch.log1p(z)
    if kind == "soft_l1":
        return 2.0 * c2 * (torch.sqrt(1.0 + z) - 1.0)
    if kind == "huber":
        return torch.where(z <= 1.0, r2, c2 * (2.0 * torch.sqrt(z.clamp_min(torch.finfo(z.dtype).tiny)) - 1.0))
    return c2 / 3.0 * (1.0 - (1.0 - z.clamp(max=1.0)) ** 3)
