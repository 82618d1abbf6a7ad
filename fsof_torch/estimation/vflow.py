"""V-flow analysis: the row histogram of the vertical flow, its eq. 24 curve, freespace detection.

The V-flow map is the optical-flow analogue of the V-disparity map: for every image row v, a
histogram of the vertical flow F_v of the pixels of that row. For straight motion of a level
camera (paper eq. 24) all road pixels of a row share one vertical flow,

    displacement flow:  F_v(v) = z_d (v - v_0)² / (h f_y - z_d (v - v_0)) = a d² / (1 - a d),
    velocity flow:      F_v(v) = v_r (v - v_0)² / (h f_y)                 = a d²,

with d = v - v_0 and a = z_d / (h f_y) (displacement, 1/px) or a = v_r / (h f_y) (velocity,
1/(px s)); so the road draws one curve in the V-flow map, while an obstacle (a surface at
roughly constant depth) draws a flatter line off it. :func:`fit_vflow_curve` finds the curve
robustly (RANSAC over rows, then iteratively reweighted Gauss–Newton), and
:func:`detect_freespace` uses it as the seed of a full model fit
(:func:`fsof_torch.fit.fit_displacement`) whose agreement with the flow, kept connected to the
bottom of the image, is the freespace.

Convention: flow (B, 2, H, W) in pixels (or px/s for velocity flow), channel 1 = v (down);
rows are indexed by the pixel-centre coordinate v = 0 … H-1; masks (B, 1, H, W) bool.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from .._check import (batch_choices, check_float_tensor, check_has_values, check_int, check_same_device,
                      check_shape, inference, is_number, option_error, result_dtype, scalar, summary_repr)
from ..geometry.camera import Camera
from ..geometry.road_flow import curve_arguments
from .solver import ResidualProblem, solve

__all__ = [
    "VFlowMap",
    "VFlowCurve",
    "vflow_map",
    "row_dominant_flow",
    "vflow_curve_model",
    "fit_vflow_curve",
]

_MODELS = ("displacement", "velocity")


class VFlowMap(NamedTuple):
    """``histogram`` (B, H, bins): per row, the (mask-weighted) count of pixels whose vertical
    flow falls in each bin; ``edges`` (bins + 1,): the bin edges in pixels (px/s for velocity
    flow), shared by the batch; bin k holds ``edges[k] <= F_v < edges[k+1]`` (the last bin
    also holds its upper edge: ``edges[-1]`` is the range's upper bound itself), as
    ``numpy.histogram`` bins."""

    histogram: Tensor
    edges: Tensor

    __repr__ = summary_repr  # (one line: the histogram as its shape)


def check_flow_mask(flow: Tensor, mask: Tensor | None) -> tuple[dict[str, int], Tensor]:
    """Validate ``flow`` (B,2,H,W) and ``mask`` (B,1,H,W) or None; return the usable pixels:
    inside the mask and with a finite vertical flow (NaN flow is treated as missing)."""
    check_float_tensor(flow, "flow")
    dims = check_shape(flow, "flow", ("B", 2, "H", "W"))
    if mask is None:
        use = torch.ones_like(flow[:, 1:2], dtype=torch.bool)
    else:
        if not isinstance(mask, Tensor):
            raise TypeError(f"mask: expected a bool tensor of shape (B, 1, H, W), got {type(mask).__name__}")
        if mask.dtype != torch.bool:
            raise TypeError(f"mask: expected dtype torch.bool, got {mask.dtype}")
        check_shape(mask, "mask", ("B", 1, "H", "W"), dims)
        check_same_device({"flow": flow, "mask": mask})
        use = mask
    return dims, use & torch.isfinite(flow[:, 1:2])


def vflow_map(flow: Tensor, mask: Tensor | None = None, *, bins: int = 128,
              max_flow: float | None = None, min_flow: float | None = None) -> VFlowMap:
    """The V-flow map: per image row, a histogram of the vertical flow (the analogue of V-disparity).

    Args:
        flow: (B, 2, H, W) flow in pixels (or px/s); channel 1, the vertical flow, is used.
        mask: (B, 1, H, W) bool, the pixels to count (default: all). Pixels with a non-finite
            vertical flow are never counted.
        bins: number of histogram bins (>= 2).
        max_flow, min_flow: the histogram range in the flow's unit. Defaults: the largest vertical
            flow in the mask over the whole batch, and min(0, the smallest one). Flows outside the
            range are not counted. Given both, ``max_flow > min_flow`` (else ValueError, as
            ``numpy.histogram``'s ``range``). A given bound is always kept: where the data's
            default for the other leaves no range (a ``max_flow`` at or below every flow and 0, a
            ``min_flow`` at or above every flow), the other lies 1 beyond it, as for an empty or
            constant map (whose range is [min, min + 1]), and the histogram holds no flow beyond
            the given bound.

    Returns:
        :class:`VFlowMap` ``(histogram (B, H, bins), edges (bins + 1,))``, both in the flow's
        dtype, float32 for half precision (pixel counts; the edges in the flow's unit).

    Example:
        >>> flow = torch.zeros(1, 2, 4, 5); flow[:, 1] = torch.arange(4.).reshape(4, 1)
        >>> hist, edges = vflow_map(flow, bins=4, max_flow=4.0)
        >>> hist[0].argmax(-1).tolist()
        [0, 1, 2, 3]
    """
    dims, use = check_flow_mask(flow, mask)
    bins, min_flow, max_flow = _histogram_options(bins, min_flow, max_flow)
    B, H = dims["B"], dims["H"]
    dtype = result_dtype(flow)
    fv = flow[:, 1].to(dtype)
    use = use[:, 0]
    lo, hi = _histogram_range(fv, use, min_flow, max_flow)
    steps = torch.arange(bins, dtype=dtype, device=flow.device) / bins
    # (a range wider than the dtype's largest number, as between flows of ±3e38 in float32, is
    # stepped through in halves: hi - lo overflows to inf, and inf · 0 gave a NaN first edge)
    half = hi / 2 - lo / 2
    inner = torch.where(torch.isfinite(hi - lo), lo + (hi - lo) * steps, lo + half * steps + half * steps)
    edges = torch.cat([inner, hi.reshape(1)])
    inside = use & (fv >= lo) & (fv <= hi)
    idx = _bin_index(torch.where(inside, fv, lo), edges)
    rows = torch.arange(B * H, device=flow.device).reshape(B, H, 1)
    flat = (rows * bins + idx).reshape(-1)
    hist = torch.zeros(B * H * bins, dtype=dtype, device=flow.device)
    hist.scatter_add_(0, flat, inside.to(dtype).reshape(-1))
    return VFlowMap(hist.reshape(B, H, bins), edges)


def _bin_index(fv: Tensor, edges: Tensor) -> Tensor:
    """The bin k of each value by comparison with the edges, ``edges[k] <= fv < edges[k+1]``, the
    last bin holding its upper edge too (-1 below the edges, ``bins`` above them or NaN). (The
    affine formula floor((fv - lo) / (hi - lo) · bins) put values on an edge into the bin below
    it, by rounding, for about one edge in ten in float32.)"""
    bins = edges.numel() - 1
    k = torch.bucketize(fv.contiguous(), edges, right=True) - 1  # (a view of one channel is not)
    return torch.where(fv == edges[-1], bins - 1, k)


def _histogram_options(bins: object, min_flow: object, max_flow: object) -> tuple[int, object, object]:
    """The V-flow histogram's options checked: ``bins`` an integer >= 2, ``min_flow`` and
    ``max_flow`` finite numbers or None (0-d tensors read), ``max_flow > min_flow`` where both
    are given; returned as (int, number or None, number or None)."""
    bins = scalar(bins, "bins")  # (a 0-d integer tensor as its int)
    if not is_number(bins, integer=True) or bins < 2:
        raise option_error(bins, f"bins: expected an integer >= 2, got {bins!r}", integer=True)
    min_flow, max_flow = scalar(min_flow, "min_flow"), scalar(max_flow, "max_flow")
    for name, value in (("min_flow", min_flow), ("max_flow", max_flow)):
        if value is not None and not (is_number(value) and abs(float(value)) < float("inf")):
            raise option_error(value, f"{name}: expected a finite number or None, got {value!r}")
    if min_flow is not None and max_flow is not None and not float(max_flow) > float(min_flow):
        raise ValueError(f"max_flow: expected > min_flow, got max_flow={max_flow!r}, min_flow={min_flow!r}")
    return int(bins), min_flow, max_flow  # (a NumPy integer too)


def _histogram_range(fv: Tensor, use: Tensor, min_flow: float | None,
                     max_flow: float | None) -> tuple[Tensor, Tensor]:
    """(lo, hi) as 0-d tensors; defaults from the data in the mask (the options checked by
    :func:`_histogram_options`)."""
    zero = fv.new_zeros(())
    if max_flow is None:
        hi = torch.where(use, fv, torch.full_like(fv, -float("inf"))).amax() if fv.numel() else zero
        hi = torch.where(torch.isfinite(hi), hi, zero)
    else:
        hi = fv.new_tensor(float(max_flow))
    if min_flow is None:
        lo = torch.where(use, fv, torch.full_like(fv, float("inf"))).amin() if fv.numel() else zero
        lo = torch.minimum(torch.where(torch.isfinite(lo), lo, zero), zero)
    else:
        lo = fv.new_tensor(float(min_flow))
    # An empty or constant map, or a given bound that the data's default for the other does not
    # leave a range with, still needs a non-empty range: the given bound stays, the other moves
    if max_flow is not None and min_flow is None:
        return torch.where(hi > lo, lo, hi - 1.0), hi
    return lo, torch.where(hi > lo, hi, lo + 1.0)


def row_dominant_flow(flow: Tensor, mask: Tensor | None = None, *, statistic: str = "peak",
                      bins: int = 128, max_flow: float | None = None,
                      min_flow: float | None = None) -> tuple[Tensor, Tensor]:
    """The dominant vertical flow of every row: the V-flow map's peak, or the row median.

    ``statistic="peak"``: the histogram's highest bin, refined to the mean of the flows falling
    in that bin and its two neighbours (so the value is not quantised to the bin width);
    the support is the number of those pixels. ``statistic="median"``: the median of the row's
    vertical flows in the mask (of an even count, the mean of the middle two); the support is the
    row's pixel count.

    Each frame's histogram range is its own (where ``min_flow`` / ``max_flow`` are not given):
    a frame gets the values it gets alone, whatever the batch's other frames hold.

    Returns:
        ``value`` (B, H) in the flow's unit (0 where a row has no pixel) and ``support`` (B, H),
        the number of pixels behind each value (0: no value).
    """
    if statistic not in ("peak", "median"):
        raise ValueError(f"statistic: expected 'peak' or 'median', got {statistic!r}")
    dims, use = check_flow_mask(flow, mask)
    # (checked whatever the statistic: the median reads no histogram, but a bad option is an error)
    bins, min_flow, max_flow = _histogram_options(bins, min_flow, max_flow)
    if statistic == "peak" and dims["B"] > 1 and (min_flow is None or max_flow is None):
        parts = [row_dominant_flow(flow[b:b + 1], use[b:b + 1], statistic="peak", bins=bins, max_flow=max_flow,
                                   min_flow=min_flow) for b in range(dims["B"])]
        return torch.cat([v for v, _ in parts]), torch.cat([n for _, n in parts])
    dtype = result_dtype(flow)
    fv = flow[:, 1].to(dtype)
    use = use[:, 0]
    if statistic == "median":
        nan = torch.full_like(fv, float("nan"))
        # the median of an even count is the mean of the middle two: torch's nanmedian takes the
        # lower, and the lower of the values negated is the upper one negated
        row = torch.where(use, fv, nan)
        value = 0.5 * (torch.nanmedian(row, dim=-1).values - torch.nanmedian(-row, dim=-1).values)
        support = use.to(dtype).sum(-1)
        return torch.where(support > 0, value, torch.zeros_like(value)), support
    hist, edges = vflow_map(flow, use.unsqueeze(1), bins=bins, max_flow=max_flow, min_flow=min_flow)
    peak = hist.argmax(-1, keepdim=True)  # (B, H, 1)
    lo, hi = edges[0], edges[-1]
    near = use & (fv >= lo) & (fv <= hi) & ((_bin_index(fv, edges) - peak).abs() <= 1)
    support = near.to(dtype).sum(-1)
    total = torch.where(near, fv, torch.zeros_like(fv)).sum(-1)
    value = total / support.clamp_min(1)
    return value, support


def vflow_curve_model(v: Tensor, a: Tensor, v0: Tensor, model: str = "displacement") -> Tensor:
    """The eq. 24 curve in the fitted parameterisation, broadcasting like tensor arithmetic.

    ``displacement``: F_v = a d² / (1 - a d); ``velocity``: F_v = a d², with d = v - v0.
    Where the curve is undefined (d <= 0: at or above the horizon; 1 - a d <= 0: the road point
    passes behind the camera) the value is 0. Differentiable in ``a`` and ``v0`` (0 where
    undefined).

    Each argument is a tensor or a number (or a sequence of numbers); the result is in their
    promoted float dtype with half precision lifted to float32 (the default dtype where none is
    a float tensor), as :func:`fsof_torch.vflow_curve`'s. A NaN or inf value is a ValueError
    naming the argument (it would read as "no road flow" there); shapes that do not broadcast
    together a ValueError quoting them (values are not checked while tracing).
    """
    if model not in _MODELS:
        raise ValueError(f"model: expected one of {_MODELS}, got {model!r}")
    args = curve_arguments({"v": v, "a": a, "v0": v0})
    return _curve(args["v"], args["a"], args["v0"], model)[0]


def _curve(v: Tensor, a: Tensor, v0: Tensor, model: str) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Curve value, ∂/∂a, ∂/∂v0 and the definedness mask."""
    d = v - v0
    if model == "velocity":
        ok = d > 0
        f, da, dv0 = a * d * d, d * d, -2.0 * a * d
    else:
        q = 1.0 - a * d
        ok = (d > 0) & (q > 0)
        qs = torch.where(ok, q, torch.ones_like(q))
        f = a * d * d / qs
        da = d * d / (qs * qs)
        dv0 = -a * d * (2.0 - a * d) / (qs * qs)
    z = torch.zeros_like(f)
    return torch.where(ok, f, z), torch.where(ok, da, z), torch.where(ok, dv0, z), ok


@dataclass(eq=False, repr=False)
class VFlowCurve:
    """The fitted eq. 24 curve of a batch of flows (compared by identity, as a :class:`Camera` is).

    Attributes:
        model: ``"displacement"`` or ``"velocity"``.
        a: (B,) curvature parameter: z_d / (h f_y) in 1/px (displacement) or v_r / (h f_y) in
            1/(px·s) (velocity), for a level camera; z_d cos²β / (h f_y) for a camera pitched by β
            (:meth:`scale` converts it).
        v0: (B,) the row of the horizon in pixels (the curve's zero).
        row_value: (B, H) the dominant vertical flow of each row that was fitted.
        row_support: (B, H) the pixel count behind each row value (0: no pixel); a row with
            fewer than ``min_row_pixels`` is not used by the fit (neither inlier nor outlier).
        row_inliers: (B, H) bool, rows that agree with the curve.
        fitted: (B, 1, H, W) the fitted F_v map (the curve evaluated on every row; 0 where
            undefined).
        fitted_valid: (B, 1, H, W) bool, where the curve is defined (below v0).
        residual: (B,) mean absolute row residual over the inlier rows (flow unit).
        nfa: (B,) the curve's number of false alarms: how many curves would be expected to fit
            as many rows as well by chance, were the usable rows' values shuffled (a-contrario, as
            in ORSA, at the best of 11 precisions of the inlier band; 1 with fewer than 3 usable
            rows, which draw no curve). Near 0 for a road; 1 or more for noise.
        success: (B,) bool: finite parameters from enough inlier rows, more than chance gives
            (``nfa`` below ``max_false_alarms``), on a curve that is determined: a ≠ 0 and the
            curve beyond the row threshold on at least one inlier row (flow without curvature,
            e.g. none at all, leaves the horizon v0 arbitrary).
    """

    model: str
    a: Tensor
    v0: Tensor
    row_value: Tensor
    row_support: Tensor
    row_inliers: Tensor
    fitted: Tensor
    fitted_valid: Tensor
    residual: Tensor
    nfa: Tensor
    success: Tensor
    __repr__ = summary_repr

    def scale(self, camera: Camera) -> Tensor:
        """z_d in metres (displacement) or v_r in m/s (velocity) under the camera's h, f_y and
        pitch β: a·h·f_y / cos²β, (B,).

        A pitched camera still sees the road draw the curve exactly, around its horizon row, with
        a = z_d cos²β / (h f_y) (resp. v_r cos²β / (h f_y)): a road point at depth z_c along the
        optical axis lies d = h f_y / (z_c cos β) below the horizon, and moving by z_d shortens
        z_c by z_d cos β. (The camera's roll spreads a row's flow instead: docs/vflow.md.)"""
        if not isinstance(camera, Camera):
            raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
        B = self.a.shape[0]
        if camera.batch_size not in (1, B):
            raise ValueError(f"camera: expected batch {batch_choices(B)} (from the curve), got {camera.batch_size}")
        return self.a * (camera.height * camera.fy / torch.cos(camera.pitch).square()).to(self.a)


@inference
def fit_vflow_curve(flow: Tensor, mask: Tensor | None = None, *, model: str = "displacement",
                    statistic: str = "peak", bins: int = 256, max_flow: float | None = None,
                    min_row_pixels: int = 3, inlier_threshold: float = 0.5,
                    relative_threshold: float = 0.05, hypotheses: int = 256,
                    iterations: int = 20, min_inlier_rows: int = 5, max_false_alarms: float = 1.0,
                    seed: int = 0) -> VFlowCurve:
    """Robust fit of the eq. 24 curve to the per-row dominant vertical flow.

    Each row contributes one value (:func:`row_dominant_flow`: the V-flow map's peak or the row
    median). Obstacles and mask errors corrupt whole rows, so the fit is robust over rows:
    RANSAC on 3-row samples of the curve's linearised form (displacement:
    ``F = p1 (v² + F v) - p2 (2v + F) + p3``; velocity: ``F = p1 v² + p2 v + p3``; then a = p1,
    v0 = p2/p1 resp. -p2/(2 p1)), scored by the support-weighted count of rows within
    ``max(inlier_threshold, relative_threshold·|F|)`` of the exact curve, then damped
    Gauss–Newton (float64) on (a, v0) with Tukey weights over the rows.

    Args:
        flow: (B, 2, H, W) displacement flow in pixels, or velocity flow in px/s.
        mask: (B, 1, H, W) bool, the pixels to use (default all; non-finite flow is skipped).
        model: ``"displacement"`` (rational curve) or ``"velocity"`` (quadratic).
        statistic: ``"peak"`` or ``"median"`` (see :func:`row_dominant_flow`).
        bins, max_flow: V-flow histogram options for ``statistic="peak"`` (checked with
            ``"median"`` too).
        min_row_pixels: rows with less support are not used.
        inlier_threshold, relative_threshold: a row is an inlier when its residual is below
            ``max(inlier_threshold, relative_threshold·|F|)`` (flow unit).
        hypotheses: number of RANSAC samples per frame.
        iterations: Gauss–Newton iterations.
        min_inlier_rows: fewer inlier rows mark the frame as failed.
        max_false_alarms: the a-contrario bar on chance (``nfa`` in :class:`VFlowCurve`): a curve
            that this many or more curves would match as well on rows whose values were
            shuffled fails. The default 1 is the usual a-contrario choice; lower is stricter.
        seed: an int with 0 <= seed < 2**64 (a torch.Generator's seeds), seeding the RANSAC
            sampling (same call, same result); each frame's draws depend only on its own rows
            and the seed (a frame gets in a batch what it gets alone).

    Returns:
        :class:`VFlowCurve`; frames that could not be fitted, or whose rows draw no curve (see
        ``success``), have ``success`` False and a = v0 = 0. Detached: a fit is not
        differentiable (its rows, samples and weights are decisions).

    Example:
        >>> from fsof_torch.flow_model import displacement_flow
        >>> cam = Camera(torch.tensor([[300., 0, 80], [0, 300, 20], [0, 0, 1]], dtype=torch.float64), 1.5)
        >>> flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, (64, 160))
        >>> curve = fit_vflow_curve(flow, valid)
        >>> round(float(curve.scale(cam)), 6), round(float(curve.v0), 6)
        (1.0, 20.0)
    """
    if model not in _MODELS:
        raise ValueError(f"model: expected one of {_MODELS}, got {model!r}")
    hypotheses, iterations, min_row_pixels, min_inlier_rows = (scalar(v, n) for n, v in (
        ("hypotheses", hypotheses), ("iterations", iterations), ("min_row_pixels", min_row_pixels),
        ("min_inlier_rows", min_inlier_rows)))  # (0-d integer tensors as their ints)
    for name, value, low in (("hypotheses", hypotheses, 1), ("iterations", iterations, 0),
                             ("min_row_pixels", min_row_pixels, 1), ("min_inlier_rows", min_inlier_rows, 3)):
        if not is_number(value, integer=True) or value < low:
            raise option_error(value, f"{name}: expected an integer >= {low}, got {value!r}", integer=True)
    inlier_threshold, relative_threshold = scalar(inlier_threshold, "inlier_threshold"), scalar(relative_threshold,
                                                                                                 "relative_threshold")
    max_false_alarms = scalar(max_false_alarms, "max_false_alarms")
    for name, value in (("inlier_threshold", inlier_threshold), ("relative_threshold", relative_threshold)):
        if not (is_number(value) and 0 <= float(value) < float("inf")):
            raise option_error(value, f"{name}: expected a finite number >= 0, got {value!r}")
    if not (is_number(max_false_alarms) and 0 < float(max_false_alarms) < float("inf")):
        raise option_error(max_false_alarms, f"max_false_alarms: expected a finite number > 0, got {max_false_alarms!r}")
    seed = check_int(seed, "seed")
    if not 0 <= seed < 2**64:  # a Generator's range; a negative seed would alias a large one
        raise ValueError(f"seed: expected an int with 0 <= seed < 2**64, got {seed!r}")
    dims, _ = check_flow_mask(flow, mask)
    if dims["B"] == 0:
        raise ValueError(f"flow: expected a non-empty batch, got shape {tuple(flow.shape)}")
    check_has_values(flow, "flow", "to fit the V-flow curve to (a robust fit reads values)")
    B, H, W = dims["B"], dims["H"], dims["W"]
    out_dtype = result_dtype(flow)
    value, support = row_dominant_flow(flow, mask, statistic=statistic, bins=bins, max_flow=max_flow)
    y = value.double()
    n = support.double()
    usable = n >= min_row_pixels
    v = torch.arange(H, dtype=torch.float64, device=flow.device).expand(B, H)
    thr = torch.clamp(relative_threshold * y.abs(), min=float(inlier_threshold))

    a, v0 = _ransac_rows(v, y, n, usable, thr, model, hypotheses, seed)
    inl = usable
    for _ in range(2):  # refine, re-select the inliers, refine again
        f = _curve(v, a.unsqueeze(-1), v0.unsqueeze(-1), model)[0]
        inl = usable & ((y - f).abs() <= thr)
        a, v0 = _gauss_newton_rows(v, y, inl, thr, a, v0, model, iterations)
    f = _curve(v, a.unsqueeze(-1), v0.unsqueeze(-1), model)[0]
    inl = usable & ((y - f).abs() <= thr)
    n_inl = inl.sum(-1)
    residual = torch.where(inl, (y - f).abs(), torch.zeros_like(y)).sum(-1) / n_inl.clamp_min(1)
    # a curve within the row threshold of 0 on every inlier row (a = 0: no motion, no curvature)
    # explains them no better than no curve: its horizon v0 is arbitrary
    drawn = (a != 0) & (inl & (f.abs() > thr)).any(-1)
    nfa = _false_alarms(y, f, thr, usable)
    success = ((n_inl >= min_inlier_rows) & (nfa < max_false_alarms) & drawn
               & torch.isfinite(a) & torch.isfinite(v0))
    a = torch.where(success, a, torch.zeros_like(a))
    v0 = torch.where(success, v0, torch.zeros_like(v0))
    fitted, _, _, ok = _curve(v, a.unsqueeze(-1), v0.unsqueeze(-1), model)
    ok = ok & success.unsqueeze(-1)
    fitted = fitted.to(out_dtype).reshape(B, 1, H, 1).expand(B, 1, H, W)
    ok = ok.reshape(B, 1, H, 1).expand(B, 1, H, W)
    return VFlowCurve(model=model, a=a.to(out_dtype), v0=v0.to(out_dtype), row_value=value,
                      row_support=support, row_inliers=inl, fitted=fitted, fitted_valid=ok,
                      residual=residual.to(out_dtype), nfa=nfa.to(out_dtype), success=success)


#: The precisions at which a curve's chance is judged: fractions of the rows' inlier band (as the
#: line segment detector judges at a few precisions): a curve whose rows lie well inside the band
#: is judged at the precision they reach, not only at the band's (a road of 1.5 px of flow whose
#: rows all agree to 1e-6 px is no chance curve, though a 1 px band holds most of its values).
_PRECISIONS = tuple(2.0 ** -i for i in range(11))


def _false_alarms(y: Tensor, f: Tensor, thr: Tensor, usable: Tensor) -> Tensor:
    """The curve's number of false alarms (a-contrario; Moisan and Stival's ORSA), (B,).

    The null hypothesis: the usable rows' values in a random order. At a precision α (a fraction
    of the inlier band), row v is an inlier when ``|y_v - f_v| <= α thr_v``; under the null
    hypothesis with probability p_v, the share of the usable rows' values y_j inside row v's band
    (``|y_j - f_v| <= α thr_j``, the inlier test applied to y_j). A curve is drawn through 3 rows,
    so the count beyond them is at most Binomial(n - 3, mean p_v) in its upper tail (Hoeffding
    1956: of the sums of independent Bernoulli variables with one mean, the binomial has the
    heaviest tail beyond the mean plus one); C(n, 3) curves can be drawn, each judged at
    len(_PRECISIONS) precisions: NFA = min over α of
    len(_PRECISIONS) · C(n, 3) · P(Binomial(n - 3, p(α)) >= k(α) - 3), n usable rows, k(α) inliers.
    """
    B, H = y.shape
    n = usable.sum(-1).double()
    beyond = torch.full_like(y, math.inf)  # (an unusable row's band, which no curve value reaches)
    inside = []
    for a in _PRECISIONS:
        # the usable rows j with y_j - a thr_j <= f_v <= y_j + a thr_j, for every row v: those whose
        # band starts at or below f_v less those whose band ends below it (sorted, not H × H pairs)
        lo = torch.where(usable, y - a * thr, beyond).sort(-1).values
        hi = torch.where(usable, y + a * thr, beyond).sort(-1).values
        count = torch.searchsorted(lo, f, right=True) - torch.searchsorted(hi, f)   # (B, H)
        inside.append(torch.where(usable, count, 0).sum(-1))
    p = (torch.stack(inside, -1).double() / n.clamp_min(1).square().unsqueeze(-1)).clamp(0, 1)   # (B, A)
    alpha = torch.tensor(_PRECISIONS, dtype=y.dtype, device=y.device)
    near = (y - f).abs().unsqueeze(-1) <= alpha * thr.unsqueeze(-1)                  # (B, H, A)
    k = (near & usable.unsqueeze(-1)).sum(1).double()                                 # (B, A)
    trials = (n - 3).clamp_min(0).reshape(B, 1, 1)
    j = torch.arange(H + 1, dtype=torch.float64, device=y.device).reshape(1, 1, H + 1)
    q = p.unsqueeze(-1)
    log_pmf = (torch.lgamma(trials + 1) - torch.lgamma(j + 1) - torch.lgamma((trials - j).clamp_min(0) + 1)
               + torch.special.xlogy(j, q) + torch.special.xlog1py(trials - j, -q))  # (B, A, H + 1)
    tail = (j >= (k - 3).unsqueeze(-1)) & (j <= trials)
    log_tail = torch.logsumexp(torch.where(tail, log_pmf, torch.full_like(log_pmf, -torch.inf)), -1).amin(-1)
    log_tests = (torch.lgamma(n + 1) - torch.lgamma((n - 2).clamp_min(1)) - math.lgamma(4)  # log C(n, 3)
                 + math.log(len(_PRECISIONS)))
    return torch.where(n >= 3, torch.exp(log_tests + log_tail), torch.ones_like(n))   # no curve: chance


def _ransac_rows(v: Tensor, y: Tensor, n: Tensor, usable: Tensor, thr: Tensor, model: str,
                 hypotheses: int, seed: int) -> tuple[Tensor, Tensor]:
    """Best (a, v0) per frame over 3-row samples of the linearised curve, (B,) each."""
    B, H = y.shape
    gen = torch.Generator(device=y.device)
    prob = usable.double() + 1e-12  # an all-unusable frame still samples (and then fails)
    # each frame draws from the generator seeded afresh: its samples depend on its own rows and
    # the seed only (in a batch it draws what it draws alone)
    draws = [torch.multinomial(prob[b:b + 1], 3 * hypotheses, replacement=True,
                               generator=gen.manual_seed(seed)) for b in range(B)]
    idx = torch.cat(draws).reshape(B, hypotheses, 3)
    vs, ys = v.gather(1, idx.reshape(B, -1)).reshape(B, hypotheses, 3), y.gather(1, idx.reshape(B, -1)).reshape(B, hypotheses, 3)
    if model == "velocity":
        A = torch.stack([vs * vs, vs, torch.ones_like(vs)], dim=-1)
    else:
        A = torch.stack([vs * vs + ys * vs, -(2 * vs + ys), torch.ones_like(vs)], dim=-1)
    sol, info = torch.linalg.solve_ex(A, ys.unsqueeze(-1))
    p = sol.squeeze(-1)
    a = p[..., 0]
    a_safe = torch.where(a != 0, a, torch.ones_like(a))
    v0 = -p[..., 1] / (2 * a_safe) if model == "velocity" else p[..., 1] / a_safe
    f, _, _, defined = _curve(v.unsqueeze(1), a.unsqueeze(-1), v0.unsqueeze(-1), model)  # (B, S, H)
    # a curve is defined on some row of the image (below its horizon): a nearly collinear sample (a
    # wall's flow) can solve to a ≈ 0 with the horizon ~1e15 px below the image, a curve defined
    # nowhere, whose zero would score every row of small flow as an inlier
    good = (info == 0) & torch.isfinite(a) & torch.isfinite(v0) & (a != 0) & defined.any(-1)
    inl = usable.unsqueeze(1) & ((y.unsqueeze(1) - f).abs() <= thr.unsqueeze(1))
    score = torch.where(inl, n.unsqueeze(1), torch.zeros_like(f)).sum(-1)
    score = torch.where(good, score, torch.full_like(score, -1.0))
    best = score.argmax(-1, keepdim=True)
    a_best = a.gather(1, best).squeeze(1)
    v0_best = v0.gather(1, best).squeeze(1)
    zero = torch.zeros_like(a_best)
    return torch.where(torch.isfinite(a_best), a_best, zero), torch.where(torch.isfinite(v0_best), v0_best, zero)


def _gauss_newton_rows(v: Tensor, y: Tensor, rows: Tensor, thr: Tensor, a: Tensor, v0: Tensor,
                       model: str, iterations: int) -> tuple[Tensor, Tensor]:
    """(a, v0) by the library's robust solver over the given rows: Tukey's biweight on the row
    residuals measured in units of twice each row's threshold (so one kernel serves rows whose
    tolerance grows with their flow)."""
    c = 2.0 * thr

    def residual(p: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        f, da, dv0, _ = _curve(v, p[:, :1], p[:, 1:], model)
        r = ((f - y) / c).unsqueeze(1)                                     # (B, 1, H)
        J = torch.stack([da / c, dv0 / c], dim=1).unsqueeze(2)             # (B, 2, 1, H)
        return r, J, rows

    start = torch.stack([a, v0], dim=-1)
    if iterations == 0:
        return a, v0
    sol = solve(ResidualProblem(residual, rows.sum(1)), start, kernel="tukey", scale=1.0,
                max_iter=iterations, damping=1e-3, check_every=None)
    good = torch.isfinite(sol.params).all(-1, keepdim=True)
    out = torch.where(good, sol.params, start)
    return out[:, 0], out[:, 1]
