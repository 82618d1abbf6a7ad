"""Flow accuracy against ground truth: the paper's e_A, e_E, e_U, e_V (eq. 25-28) and KITTI's Fl.

Per pixel, with F the estimate and F̂ the ground truth (both (u, v) in pixels):

- e_A = arccos( (⟨F, F̂⟩ + 1) / sqrt((‖F‖² + 1)(‖F̂‖² + 1)) ), radians: the angle between the
  space-time vectors (u, v, 1) and (û, v̂, 1). Computed as atan2(‖a × b‖, a · b), which equals
  the arccos with its argument clamped to [-1, 1] but keeps float32 accuracy for small angles
  (a float32 arccos cannot resolve angles below about 3e-4 rad) and has finite gradients.
- e_E = ‖F − F̂‖₂ (end-point error, px); e_U = |u − û|, e_V = |v − v̂| (px).
- Fl = 1 where e_E > 3 px and e_E > 5% of ‖F̂‖ (KITTI 2015 outlier), else 0.

Which pixels count: ``mask`` (where to evaluate, e.g. the road) and ``valid`` (where the ground
truth exists, e.g. KITTI's sparse laser points), both optional (B, 1, H, W) bool; the metrics
average over pixels where both are True. Two reductions:

- per sample (B,): the functions :func:`angular_error`, :func:`endpoint_error`, :func:`u_error`,
  :func:`v_error`, :func:`outlier_rate` and :func:`flow_metrics_per_sample`;
- over all counted pixels of the batch at once, KITTI style (a frame with many valid pixels
  weighs more): :func:`flow_metrics`, returning Python floats and the pixel count.

Empty selections: a mean over zero pixels is reported as 0.0 with a count of 0, never NaN; the
count (``return_count=True``, or ``n_pixels``) is the flag to check. Fl is a fraction in [0, 1]
(KITTI prints it in percent).
"""

from __future__ import annotations

import torch
from torch import Tensor

from .._check import check_float_tensor, check_shape, result_dtype

__all__ = [
    "flow_error_maps",
    "angular_error",
    "endpoint_error",
    "u_error",
    "v_error",
    "outlier_rate",
    "flow_metrics",
    "flow_metrics_per_sample",
    "METRIC_NAMES",
]

METRIC_NAMES = ("e_A", "e_E", "e_U", "e_V", "Fl")

# A per-sample mean (B,), or (mean, count (B,) int64) with return_count=True.
_Result = Tensor | tuple[Tensor, Tensor]

# KITTI 2015 outlier thresholds (devkit: ABS_THRESH = 3 px, REL_THRESH = 5%).
_FL_ABS_PX = 3.0
_FL_REL = 0.05


def _selection(flow_est: Tensor, flow_gt: Tensor, mask: Tensor | None,
               valid: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """Check the inputs; return both flows in the working dtype and the counted pixels (B,1,H,W)."""
    check_float_tensor(flow_est, "flow_est")
    check_float_tensor(flow_gt, "flow_gt")
    dims = check_shape(flow_est, "flow_est", ("B", 2, "H", "W"))
    check_shape(flow_gt, "flow_gt", ("B", 2, "H", "W"), dims)
    B, _, H, W = flow_est.shape
    sel = torch.ones(B, 1, H, W, dtype=torch.bool, device=flow_est.device)
    for name, m in (("mask", mask), ("valid", valid)):
        if m is None:
            continue
        if not isinstance(m, Tensor) or m.dtype != torch.bool:
            got = m.dtype if isinstance(m, Tensor) else type(m).__name__
            raise TypeError(f"{name}: expected a bool tensor, got {got}")
        check_shape(m, name, ("B", 1, "H", "W"), dims)
        sel = sel & m
    work = result_dtype(flow_est, flow_gt)
    # Zero the flows outside the selection: ground truth may hold NaN or 1e9 where it is invalid,
    # and torch.where on the inputs keeps both the sums and the gradients finite.
    zero = torch.zeros((), dtype=work, device=flow_est.device)
    est = torch.where(sel, flow_est.to(work), zero)
    gt = torch.where(sel, flow_gt.to(work), zero)
    return est, gt, sel


def _safe_sqrt(sq: Tensor) -> Tensor:
    """sqrt with a zero (not infinite) gradient at 0: equal flows must not give NaN gradients."""
    positive = sq > 0
    return torch.where(positive, torch.sqrt(torch.where(positive, sq, torch.ones_like(sq))),
                       torch.zeros_like(sq))


def _maps(est: Tensor, gt: Tensor) -> dict[str, Tensor]:
    u1, v1 = est[:, 0:1], est[:, 1:2]
    u2, v2 = gt[:, 0:1], gt[:, 1:2]
    # a = (u1, v1, 1), b = (u2, v2, 1): a x b and a . b.
    cross = torch.stack([v1 - v2, u2 - u1, u1 * v2 - v1 * u2])
    cross_norm = _safe_sqrt((cross * cross).sum(dim=0))
    dot = u1 * u2 + v1 * v2 + 1.0
    e_a = torch.atan2(cross_norm, dot)
    du, dv = u1 - u2, v1 - v2
    e_u, e_v = du.abs(), dv.abs()
    e_e = _safe_sqrt(du * du + dv * dv)
    mag_gt = torch.sqrt(u2 * u2 + v2 * v2)
    fl = ((e_e > _FL_ABS_PX) & (e_e > _FL_REL * mag_gt)).to(est.dtype)
    return {"e_A": e_a, "e_E": e_e, "e_U": e_u, "e_V": e_v, "Fl": fl}


def flow_error_maps(flow_est: Tensor, flow_gt: Tensor, mask: Tensor | None = None,
                    valid: Tensor | None = None) -> tuple[dict[str, Tensor], Tensor]:
    """Per-pixel errors: ``({"e_A", "e_E", "e_U", "e_V", "Fl"}: (B, 1, H, W), counted (B, 1, H, W) bool)``.

    Args:
        flow_est: (B, 2, H, W) estimated flow, pixels.
        flow_gt: (B, 2, H, W) ground-truth flow, pixels.
        mask, valid: optional (B, 1, H, W) bool; ``counted = mask & valid``.

    Returns:
        maps: e_A in radians, e_E, e_U, e_V in pixels, Fl 0/1; each 0 where not counted.
        counted: the pixels that enter the means.
    """
    est, gt, sel = _selection(flow_est, flow_gt, mask, valid)
    zero = torch.zeros((), dtype=est.dtype, device=est.device)
    return {k: torch.where(sel, m, zero) for k, m in _maps(est, gt).items()}, sel


def _per_sample(name: str, flow_est: Tensor, flow_gt: Tensor, mask: Tensor | None,
                valid: Tensor | None, return_count: bool) -> _Result:
    maps, sel = flow_error_maps(flow_est, flow_gt, mask, valid)
    count = sel.flatten(1).sum(dim=1)
    mean = maps[name].flatten(1).sum(dim=1) / count.clamp(min=1).to(maps[name].dtype)
    return (mean, count) if return_count else mean


def angular_error(flow_est: Tensor, flow_gt: Tensor, mask: Tensor | None = None,
                  valid: Tensor | None = None, *, return_count: bool = False) -> _Result:
    """Mean angular error e_A (paper eq. 25) per sample, radians: (B,) [, count (B,) int64].

    flow_est, flow_gt: (B, 2, H, W) pixels; mask, valid: optional (B, 1, H, W) bool. A sample
    with no counted pixel gets 0.0 (check the count).
    """
    return _per_sample("e_A", flow_est, flow_gt, mask, valid, return_count)


def endpoint_error(flow_est: Tensor, flow_gt: Tensor, mask: Tensor | None = None,
                   valid: Tensor | None = None, *, return_count: bool = False) -> _Result:
    """Mean end-point error e_E (paper eq. 26) per sample, pixels: (B,) [, count (B,) int64]."""
    return _per_sample("e_E", flow_est, flow_gt, mask, valid, return_count)


def u_error(flow_est: Tensor, flow_gt: Tensor, mask: Tensor | None = None,
            valid: Tensor | None = None, *, return_count: bool = False) -> _Result:
    """Mean absolute error of the u (horizontal) component, e_U (eq. 27), pixels: (B,)."""
    return _per_sample("e_U", flow_est, flow_gt, mask, valid, return_count)


def v_error(flow_est: Tensor, flow_gt: Tensor, mask: Tensor | None = None,
            valid: Tensor | None = None, *, return_count: bool = False) -> _Result:
    """Mean absolute error of the v (vertical) component, e_V (eq. 28), pixels: (B,)."""
    return _per_sample("e_V", flow_est, flow_gt, mask, valid, return_count)


def outlier_rate(flow_est: Tensor, flow_gt: Tensor, mask: Tensor | None = None,
                 valid: Tensor | None = None, *, return_count: bool = False) -> _Result:
    """KITTI Fl per sample: the fraction (0-1) of pixels with e_E > 3 px and > 5% of ‖F̂‖: (B,)."""
    return _per_sample("Fl", flow_est, flow_gt, mask, valid, return_count)


def flow_metrics_per_sample(flow_est: Tensor, flow_gt: Tensor, mask: Tensor | None = None,
                            valid: Tensor | None = None) -> dict[str, Tensor]:
    """All five metrics per sample: ``{"e_A", "e_E", "e_U", "e_V", "Fl"}: (B,)``, ``"n_pixels"``: (B,) int64.

    A sample with ``n_pixels == 0`` has all metrics 0.0.
    """
    maps, sel = flow_error_maps(flow_est, flow_gt, mask, valid)
    count = sel.flatten(1).sum(dim=1)
    denom = count.clamp(min=1)
    out = {k: m.flatten(1).sum(dim=1) / denom.to(m.dtype) for k, m in maps.items()}
    out["n_pixels"] = count
    return out


def flow_metrics(flow_est: Tensor, flow_gt: Tensor, mask: Tensor | None = None,
                 valid: Tensor | None = None) -> dict[str, float | int]:
    """The five metrics over all counted pixels of the batch at once (KITTI style), as numbers.

    Args:
        flow_est, flow_gt: (B, 2, H, W) pixels.
        mask, valid: optional (B, 1, H, W) bool.

    Returns:
        ``{"e_A": rad, "e_E": px, "e_U": px, "e_V": px, "Fl": fraction, "n_pixels": int}``.
        With ``n_pixels == 0`` every metric is 0.0 (not NaN): check ``n_pixels``.

    Example:
        >>> est = torch.tensor([1.0, 0.0]).view(1, 2, 1, 1); gt = torch.tensor([0.0, 1.0]).view(1, 2, 1, 1)
        >>> m = flow_metrics(est, gt); round(m["e_A"], 6), round(m["e_E"], 6), m["n_pixels"]
        (1.047198, 1.414214, 1)
    """
    maps, sel = flow_error_maps(flow_est, flow_gt, mask, valid)
    n = int(sel.sum())
    # Sum in float64: float32 sums over millions of pixels lose digits.
    out: dict[str, float | int] = {k: float(m.detach().double().sum()) / max(n, 1) for k, m in maps.items()}
    out["n_pixels"] = n
    return out
