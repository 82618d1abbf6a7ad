"""Flow accuracy against ground truth: the paper's e_A, e_E, e_U, e_V (eq. 25-28), KITTI's Fl and
the benchmark names ``epe``, ``fl`` / ``flall``, ``px1``, ``px3``, ``px5``.

Per pixel, with F the estimate and F̂ the ground truth (both (u, v) in pixels):

- e_A = arccos( (⟨F, F̂⟩ + 1) / sqrt((‖F‖² + 1)(‖F̂‖² + 1)) ), radians: the angle between the
  space-time vectors (u, v, 1) and (û, v̂, 1). Computed as atan2(‖a × b‖, a · b), which equals
  the arccos with its argument clamped to [-1, 1] but keeps float32 accuracy for small angles
  (a float32 arccos cannot resolve angles below about 3e-4 rad) and has finite gradients; the
  cross product is written in the differences F − F̂ (u v̂ − v û = v̂ (u − û) − û (v − v̂)), so
  nearly equal flows do not cancel it to noise.
- e_E = ‖F − F̂‖₂ (end-point error, px); e_U = |u − û|, e_V = |v − v̂| (px).
- Fl = 1 where e_E > 3 px and e_E > 5% of ‖F̂‖ (KITTI 2015 outlier), else 0.

The names benchmarks and ptlflow use: ``epe`` = e_E; ``fl`` and ``flall`` = Fl (KITTI's
"Fl-all": over all counted pixels; a fraction here, KITTI prints percent); ``px1``, ``px3``,
``px5`` = the fraction of counted pixels with e_E < 1, 3, 5 px (ptlflow's definition: higher is
better).

Which pixels count: ``mask`` (where to evaluate, e.g. the road) and ``valid`` (where the ground
truth exists, e.g. KITTI's sparse laser points), both optional (B, 1, H, W) bool, and only where
the ground truth is finite (a NaN or inf ground-truth value marks the pixel invalid, as KITTI's
valid channel does). Non-finite *estimates* at counted pixels raise ValueError naming
``flow_est``: a NaN cannot be scored, and scoring it as 0 or dropping it would let a broken
network look good. Values are scaled by powers of two before squaring, so a float32 flow of
1e20 px gives a finite e_E of the right size, and e_A stays right for flows whose cross-product
terms (about 1/|F|) would underflow when squared; a result beyond the dtype's range (an error
above 3.4e38 px in float32) raises ValueError instead of returning inf.

Reductions:

- per sample (B,): :func:`angular_error`, :func:`endpoint_error`, :func:`u_error`,
  :func:`v_error`, :func:`outlier_rate` and :func:`flow_metrics_per_sample` (every name);
- over all counted pixels of the batch at once, KITTI style (a frame with many valid pixels
  weighs more): :func:`flow_metrics`, returning Python floats and the pixel count;
- over a data set, across batches and processes: :class:`FlowMetricAccumulator` (pooled over
  pixels, KITTI, or the mean of per-image values, ptlflow).

Empty selections: a mean over zero pixels is reported as 0.0 with a count of 0, never NaN; the
count (``return_count=True``, or ``n_pixels``) is the flag to check.
:meth:`FlowMetricAccumulator.compute` over nothing counted warns as well (``RuntimeWarning``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .._check import (all_finite, check_bool, check_device, check_float_tensor, check_shape, result_dtype, skip_values,
                      to_device)
from ..warn import warn_user
from .warp import band_rows

__all__ = [
    "flow_error_maps",
    "angular_error",
    "endpoint_error",
    "u_error",
    "v_error",
    "outlier_rate",
    "flow_metrics",
    "flow_metrics_per_sample",
    "FlowMetricAccumulator",
    "METRIC_NAMES",
    "BENCHMARK_NAMES",
    "PX_THRESHOLDS",
]

METRIC_NAMES = ("e_A", "e_E", "e_U", "e_V", "Fl")
#: The benchmark names: ``epe`` is e_E, ``fl`` and ``flall`` are Fl, ``pxN`` the fraction below N px.
BENCHMARK_NAMES = ("epe", "fl", "flall", "px1", "px3", "px5")
#: The thresholds of ``px1``, ``px3``, ``px5`` in pixels.
PX_THRESHOLDS = (1.0, 3.0, 5.0)

# Every per-pixel map a reduction sums (the benchmark aliases are derived after the means).
_MAPS = METRIC_NAMES + tuple(f"px{int(t)}" for t in PX_THRESHOLDS)

# A per-sample mean (B,), or (mean, count (B,) int64) with return_count=True.
_Result = Tensor | tuple[Tensor, Tensor]

# Pixels (B H W) per band of rows of flow_error_maps without autograd: a KITTI frame is one band
_BAND_PIXELS = 1 << 19

# KITTI 2015 outlier thresholds (devkit: ABS_THRESH = 3 px, REL_THRESH = 5%).
_FL_ABS_PX = 3.0
_FL_REL = 0.05


def _check_mask(m: object, name: str, dims: dict[str, int]) -> Tensor:
    if not isinstance(m, Tensor) or m.dtype != torch.bool:
        got = m.dtype if isinstance(m, Tensor) else type(m).__name__
        raise TypeError(f"{name}: expected a bool tensor, got {got}")
    check_shape(m, name, ("B", 1, "H", "W"), dims)
    return m


def _selection(flow_est: Tensor, flow_gt: Tensor, mask: Tensor | None,
               valid: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """Check the inputs; return both flows in the working dtype and the counted pixels (B,1,H,W)."""
    check_float_tensor(flow_est, "flow_est")
    check_float_tensor(flow_gt, "flow_gt")
    dims = check_shape(flow_est, "flow_est", ("B", 2, "H", "W"))
    check_shape(flow_gt, "flow_gt", ("B", 2, "H", "W"), dims)
    if flow_gt.device != flow_est.device:
        raise ValueError(f"flow_gt: expected the device of flow_est ({flow_est.device}), got {flow_gt.device}")
    # Non-finite ground truth is not ground truth: such pixels are invalid (KITTI style).
    sel = torch.isfinite(flow_gt).all(dim=1, keepdim=True)
    for name, m in (("mask", mask), ("valid", valid)):
        if m is not None:
            sel = sel & to_device(_check_mask(m, name, dims), name, flow_est.device)
    work = result_dtype(flow_est, flow_gt)
    # Zero the flows outside the selection: ground truth may hold NaN or 1e9 where it is invalid,
    # and torch.where on the inputs keeps both the sums and the gradients finite.
    zero = torch.zeros((), dtype=work, device=flow_est.device)
    est = torch.where(sel, flow_est.to(work), zero)
    gt = torch.where(sel, flow_gt.to(work), zero)
    return est, gt, sel


def pow2_scale(*xs: Tensor, at_least_one: bool = True) -> Tensor:
    """A power of two s per element with |x| / s < 2 for every x (s >= 1 with ``at_least_one``):
    dividing by it is exact (no rounding), so scaled formulas give bit-identical results for
    ordinary values and finite ones where squares would overflow, or, without the floor of 1,
    underflow (s itself stays finite up to the dtype's largest value). Detached: results do not
    depend on it. The metrics' norms and :func:`~fsof_torch.evaluation.visualize.flow_to_color`
    use it."""
    m = xs[0].detach().abs()
    for x in xs[1:]:
        m = torch.maximum(m, x.detach().abs())
    if at_least_one:
        m = torch.clamp(m, min=1.0)
    _, exponent = torch.frexp(m)  # m = mantissa · 2^exponent, mantissa in [0.5, 1); 0 -> 2^0
    return torch.ldexp(torch.ones_like(m), exponent - 1)


def _norm(*components: Tensor, rescale: bool = False) -> Tensor:
    """Euclidean norm of components of magnitude <= 4 with a zero (not NaN) gradient at 0.

    ``rescale``: divide the components by a power of two t (:func:`pow2_scale`, no floor) that
    brings the largest below 2 before squaring, and multiply the root by t: exact, so bit for bit
    the plain formula's result wherever that does not underflow. The cross product of the angular
    error needs it: its terms are about 1/s for a flow of s px, and their squares underflow
    float32 from about 1e19 px (the other norms' components are about 1 or exactly 0)."""
    t = pow2_scale(*components, at_least_one=False) if rescale else None
    if t is not None:
        components = tuple(c / t for c in components)
    sq = components[0] * components[0]
    for c in components[1:]:
        sq = sq + c * c
    positive = sq > 0
    norm = torch.where(positive, torch.sqrt(torch.where(positive, sq, torch.ones_like(sq))),
                       torch.zeros_like(sq))
    return norm if t is None else norm * t


def _maps(est: Tensor, gt: Tensor) -> dict[str, Tensor]:
    s = pow2_scale(est[:, 0:1], est[:, 1:2], gt[:, 0:1], gt[:, 1:2])
    u1, v1 = est[:, 0:1] / s, est[:, 1:2] / s
    u2, v2 = gt[:, 0:1] / s, gt[:, 1:2] / s
    # a = (u1, v1, 1/s), b = (u2, v2, 1/s): the space-time vectors divided by s (the angle between
    # them does not change) -> a x b and a . b without overflow.
    w = 1.0 / s
    du, dv = u1 - u2, v1 - v2
    # (u1 v2 - v1 u2 written in du, dv: the products of nearly equal flows cancel to rounding noise,
    # 0.6 relative error in float32 for errors of 1e-3 px on 20 px flows; their differences are exact)
    cross_norm = _norm(dv * w, -du * w, v2 * du - u2 * dv, rescale=True)
    dot = u1 * u2 + v1 * v2 + w * w
    e_a = torch.atan2(cross_norm, dot)
    e_u, e_v = du.abs() * s, dv.abs() * s
    e_e = _norm(du, dv) * s
    mag_gt = _norm(u2, v2) * s
    maps = {"e_A": e_a, "e_E": e_e, "e_U": e_u, "e_V": e_v,
            "Fl": ((e_e > _FL_ABS_PX) & (e_e > _FL_REL * mag_gt)).to(est.dtype)}
    for t in PX_THRESHOLDS:
        maps[f"px{int(t)}"] = (e_e < t).to(est.dtype)
    return maps


def _check_counted(flow_est: Tensor, e_e: Tensor, sel: Tensor) -> None:
    """Raise where an estimate is not finite, or its error overflows, at a counted pixel."""
    if skip_values(flow_est, e_e) or (all_finite(flow_est) and all_finite(e_e)):
        return  # the common case: one reduction each, no per-pixel test
    bad_est = ~torch.isfinite(flow_est).all(dim=1, keepdim=True) & sel
    overflow = ~torch.isfinite(e_e) & sel
    n_bad, n_over = torch.stack([bad_est.sum(), overflow.sum()]).tolist()
    if n_bad:
        b, _, y, x = bad_est.nonzero()[0].tolist()
        raise ValueError(
            f"flow_est: {n_bad} non-finite value(s) (NaN or inf) at counted pixels, the first at "
            f"sample {b}, pixel (u={x}, v={y}): {flow_est[b, :, y, x].tolist()}; a metric cannot "
            f"score them (exclude them with mask/valid, or fix the prediction)")
    if n_over:
        raise ValueError(
            f"flow_est: {n_over} end-point error(s) overflow {e_e.dtype} (largest |flow_est| "
            f"{float(flow_est.detach().abs().amax()):.3g} px); evaluate in float64")


def flow_error_maps(flow_est: Tensor, flow_gt: Tensor, mask: Tensor | None = None,
                    valid: Tensor | None = None) -> tuple[dict[str, Tensor], Tensor]:
    """Per-pixel errors and the pixels that count.

    Args:
        flow_est: (B, 2, H, W) estimated flow, pixels; finite wherever it is counted.
        flow_gt: (B, 2, H, W) ground-truth flow, pixels; non-finite values mark invalid pixels.
        mask, valid: optional (B, 1, H, W) bool; ``counted = mask & valid & finite(flow_gt)``.

    Returns:
        maps: ``{"e_A", "e_E", "e_U", "e_V", "Fl", "px1", "px3", "px5"}``: (B, 1, H, W); e_A in
            radians, e_E, e_U, e_V in pixels, Fl and pxN 0/1; each 0 where not counted.
        counted: (B, 1, H, W) bool, the pixels that enter the means.

    Raises:
        ValueError: naming ``flow_est`` for a NaN or inf estimate at a counted pixel.
    """
    est, gt, sel = _selection(flow_est, flow_gt, mask, valid)
    zero = torch.zeros((), dtype=est.dtype, device=est.device)
    B, _, H, W = est.shape
    rows = band_rows(B, H, W, _BAND_PIXELS)
    if rows >= H or (torch.is_grad_enabled() and (est.requires_grad or gt.requires_grad)):
        maps = {k: torch.where(sel, m, zero) for k, m in _maps(est, gt).items()}
    else:
        # without autograd, a band of rows at a time: the formulas' temporaries (some 100 bytes a
        # pixel) exist for one band only, and each value is the one-pass value (band_rows)
        maps = {k: est.new_empty(sel.shape) for k in _MAPS}
        for top in range(0, H, rows):
            band = (slice(None), slice(None), slice(top, top + rows))
            for k, m in _maps(est[band], gt[band]).items():
                torch.where(sel[band], m, zero, out=maps[k][band])
    # (e_E outside the counted pixels is 0 here: only counted ones are checked)
    _check_counted(flow_est, maps["e_E"], sel)
    return maps, sel


def _sum_dtype(device: torch.device) -> torch.dtype:
    # Sums over millions of pixels in float64 (float32 loses digits and can overflow);
    # MPS has no float64.
    return torch.float32 if device.type == "mps" else torch.float64


def _means(maps: dict[str, Tensor], sel: Tensor) -> tuple[dict[str, Tensor], Tensor]:
    count = sel.flatten(1).sum(dim=1)
    out = {}
    for k, m in maps.items():
        total = m.flatten(1).sum(dim=1, dtype=_sum_dtype(m.device))
        out[k] = (total / count.clamp(min=1).to(total.dtype)).to(m.dtype)
    return out, count


def _with_aliases(values: dict) -> dict:
    """Add the benchmark names to a dict of METRIC_NAMES values (same numbers, two names)."""
    values["epe"] = values["e_E"]
    values["fl"] = values["Fl"]
    values["flall"] = values["Fl"]
    return values


def _per_sample(name: str, flow_est: Tensor, flow_gt: Tensor, mask: Tensor | None,
                valid: Tensor | None, return_count: bool) -> _Result:
    # (True or False: a truthy string such as "no" returned a tuple, 0 or None the mean alone)
    check_bool(return_count, "return_count")
    maps, sel = flow_error_maps(flow_est, flow_gt, mask, valid)
    means, count = _means({name: maps[name]}, sel)
    return (means[name], count) if return_count else means[name]


def angular_error(flow_est: Tensor, flow_gt: Tensor, mask: Tensor | None = None,
                  valid: Tensor | None = None, *, return_count: bool = False) -> _Result:
    """Mean angular error e_A (paper eq. 25) per sample, radians: (B,) [, count (B,) int64].

    flow_est, flow_gt: (B, 2, H, W) pixels; mask, valid: optional (B, 1, H, W) bool. A sample
    with no counted pixel gets 0.0 (check the count).
    """
    return _per_sample("e_A", flow_est, flow_gt, mask, valid, return_count)


def endpoint_error(flow_est: Tensor, flow_gt: Tensor, mask: Tensor | None = None,
                   valid: Tensor | None = None, *, return_count: bool = False) -> _Result:
    """Mean end-point error e_E (paper eq. 26, ``epe``) per sample, pixels: (B,) [, count (B,) int64]."""
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
    """KITTI Fl (``fl`` / ``flall``) per sample: the fraction (0-1) of pixels with e_E > 3 px and
    > 5% of ‖F̂‖: (B,)."""
    return _per_sample("Fl", flow_est, flow_gt, mask, valid, return_count)


def flow_metrics_per_sample(flow_est: Tensor, flow_gt: Tensor, mask: Tensor | None = None,
                            valid: Tensor | None = None) -> dict[str, Tensor]:
    """Every metric per sample (per image): (B,) tensors.

    Returns:
        ``{"e_A", "e_E", "e_U", "e_V", "Fl", "px1", "px3", "px5", "epe", "fl", "flall"}``: (B,)
        in the working dtype, the flows' promoted dtype lifted to at least float32 (float32 for
        bfloat16 or float16 flows, float64 if either flow is float64; ``epe`` is e_E, ``fl`` and
        ``flall`` are Fl), and ``"n_pixels"``: (B,) int64. A sample with ``n_pixels == 0`` has all
        metrics 0.0.
    """
    maps, sel = flow_error_maps(flow_est, flow_gt, mask, valid)
    out, count = _means(maps, sel)
    out = _with_aliases(out)
    out["n_pixels"] = count
    return out


def flow_metrics(flow_est: Tensor, flow_gt: Tensor, mask: Tensor | None = None,
                 valid: Tensor | None = None) -> dict[str, float | int]:
    """Every metric over all counted pixels of the batch at once (KITTI style), as numbers.

    Args:
        flow_est, flow_gt: (B, 2, H, W) pixels.
        mask, valid: optional (B, 1, H, W) bool.

    Returns:
        ``{"e_A": rad, "e_E": px, "e_U": px, "e_V": px, "Fl": fraction, "px1", "px3", "px5":
        fractions, "epe", "fl", "flall": the same numbers under the benchmark names,
        "n_pixels": int}``. With ``n_pixels == 0`` every metric is 0.0 (not NaN): check
        ``n_pixels``.

    Example:
        >>> est = torch.tensor([1.0, 0.0]).view(1, 2, 1, 1); gt = torch.tensor([0.0, 1.0]).view(1, 2, 1, 1)
        >>> m = flow_metrics(est, gt); round(m["e_A"], 6), round(m["e_E"], 6), m["px1"], m["n_pixels"]
        (1.047198, 1.414214, 0.0, 1)
    """
    maps, sel = flow_error_maps(flow_est, flow_gt, mask, valid)
    if skip_values(sel):
        raise ValueError("flow_est: flow_metrics returns Python numbers, which a meta tensor does "
                         "not have; use flow_metrics_per_sample for shape inference")
    sums = torch.stack([m.detach().flatten().sum(dtype=_sum_dtype(m.device)) for m in maps.values()])
    n = int(sel.sum())
    out: dict[str, float | int] = {k: v / max(n, 1) for k, v in zip(maps, sums.tolist())}
    out = _with_aliases(out)
    out["n_pixels"] = n
    return out


class FlowMetricAccumulator:
    """Sums and counts of every metric over a data set: across batches, and across processes.

    Two ways to pool, both kept at once:

    - ``compute("pixels")``: over all counted pixels of the set (KITTI's way: a frame with more
      valid pixels weighs more; what :func:`flow_metrics` does within a batch);
    - ``compute("images")``: the mean of per-image values (ptlflow's way); images without any
      counted pixel are left out of this mean (``n_images`` counts the others).

    Across processes: :meth:`all_reduce` returns the accumulator summed over every process of
    the default ``torch.distributed`` group (one ``all_reduce`` of one float64 tensor); without
    an initialised group it returns a copy of this one. :meth:`merge` adds another accumulator
    (from a worker, or a saved state) by hand. Counts are held in float64, exact up to 2^53.

    The sums are replaced, never written in place, so an accumulator built or updated under
    ``torch.inference_mode`` (whose tensors refuse in-place writes outside it) keeps working
    outside it, and the other way round.

    Example:
        >>> acc = FlowMetricAccumulator()
        >>> for est, gt, valid in batches:                            # doctest: +SKIP
        ...     acc.update(est, gt, valid=valid)
        >>> acc.all_reduce().compute()["epe"]                         # doctest: +SKIP
    """

    def __init__(self, *, device: torch.device | str | None = None) -> None:
        """``device``: where the sums are held (None: the default device), a ``torch.device``, a
        device string such as ``"cuda:0"`` or a device index; anything else a ValueError (an
        unknown string such as ``"gpu"``, an index without an accelerator, or the meta device,
        which holds no sums) or a TypeError (a bool, a float) naming ``device``."""
        device = check_device(device)  # (torch's RuntimeError for "gpu" named no argument; True would be index 1)
        n = len(_MAPS)
        # [pixel sums (n), n_pixels, per-image-mean sums (n), n_images]: one tensor, one reduction
        self.state = torch.zeros(2 * n + 2, dtype=torch.float64, device=device)
        if self.state.device.type == "meta":  # (its sums were lost there; compute() raised torch's error)
            raise ValueError(f"device: an accumulator sums values, which the meta device does not hold; got "
                             f"{self.state.device}")

    @property
    def n_pixels(self) -> int:
        """Pixels counted so far (what ``compute("pixels")`` averages over)."""
        return int(self.state[len(_MAPS)])

    @property
    def n_images(self) -> int:
        """Images with at least one counted pixel so far (what ``compute("images")`` averages over)."""
        return int(self.state[-1])

    def reset(self) -> None:
        """Forget every update (the sums back to 0, on the same device)."""
        self.state = torch.zeros_like(self.state)

    def update(self, flow_est: Tensor, flow_gt: Tensor, mask: Tensor | None = None,
               valid: Tensor | None = None) -> dict[str, Tensor]:
        """Add a batch; returns its per-image metrics as :func:`flow_metrics_per_sample` does
        (detached; the same values and dtype, at least float32)."""
        with torch.no_grad():
            maps, sel = flow_error_maps(flow_est, flow_gt, mask, valid)
            if skip_values(sel):
                raise ValueError("flow_est: an accumulator sums values, which a meta tensor does not have")
            count = sel.flatten(1).sum(dim=1)
            pixel_sums = torch.stack([m.flatten(1).sum(dim=1, dtype=torch.float64) for m in maps.values()])
            per_image = pixel_sums / count.clamp(min=1).to(torch.float64)
            has_pixels = (count > 0).to(torch.float64)
            batch = torch.cat([pixel_sums.sum(dim=1), count.sum().reshape(1).to(torch.float64),
                               (per_image * has_pixels).sum(dim=1), has_pixels.sum().reshape(1)])
            self.state = self.state + batch.to(self.state.device)
        # the working dtype of the maps (at least float32), as flow_metrics_per_sample returns
        out = {k: per_image[i].to(maps[k].dtype) for i, k in enumerate(maps)}
        out = _with_aliases(out)
        out["n_pixels"] = count
        return out

    def merge(self, other: "FlowMetricAccumulator") -> "FlowMetricAccumulator":
        """Add the sums and counts of ``other`` to this accumulator; returns self."""
        if not isinstance(other, FlowMetricAccumulator):
            raise TypeError(f"other: expected a FlowMetricAccumulator, got {type(other).__name__}")
        self.state = self.state + other.state.to(self.state.device)
        return self

    def all_reduce(self, group: object = None) -> "FlowMetricAccumulator":
        """A new accumulator holding the sums over every process of ``group`` (default: the
        world). This one keeps its local sums, so calling it twice never double-counts. Without
        an initialised process group (one process) the copy equals this accumulator. With the
        nccl backend, build the accumulator with ``device`` set to the process's GPU."""
        out = FlowMetricAccumulator(device=self.state.device)
        out.state = self.state.clone()
        import torch.distributed as dist

        if dist.is_available() and dist.is_initialized():
            dist.all_reduce(out.state, op=dist.ReduceOp.SUM, group=group)
        return out

    def compute(self, reduction: str = "pixels") -> dict[str, float | int]:
        """The metrics as numbers: ``{"e_A", "e_E", "e_U", "e_V", "Fl", "px1", "px3", "px5",
        "epe", "fl", "flall", "n_pixels", "n_images"}``; 0.0 (not NaN) when nothing was counted,
        with a ``RuntimeWarning`` saying so (an end-point error of 0.0 reads as a perfect result).

        Args:
            reduction: ``"pixels"`` (pooled over all counted pixels, KITTI) or ``"images"`` (the
                mean of per-image values, ptlflow).
        """
        if reduction not in ("pixels", "images"):
            raise ValueError(f"reduction: expected 'pixels' or 'images', got {reduction!r}")
        n = len(_MAPS)
        values = self.state.tolist()
        sums, count = (values[:n], values[n]) if reduction == "pixels" else (values[n + 1:-1], values[-1])
        if count == 0:
            # (the 0.0 that stands for "nothing counted" was returned without a word: a data set whose
            # valid masks all came out False, e.g. inverted, evaluated to a perfect end-point error)
            warn_user(f"FlowMetricAccumulator.compute({reduction!r}): nothing was counted (n_pixels "
                      f"{int(values[n])}, n_images {int(values[-1])}); every metric is 0.0, which is no "
                      f"result: check the mask and valid passed to update()")
        out: dict[str, float | int] = {k: s / max(count, 1.0) for k, s in zip(_MAPS, sums)}
        out = _with_aliases(out)
        out["n_pixels"] = int(values[n])
        out["n_images"] = int(values[-1])
        return out

    def state_dict(self) -> dict[str, Tensor]:
        """``{"state": tensor}``, a copy of the running sums, for :meth:`load_state_dict`."""
        return {"state": self.state.clone()}

    def load_state_dict(self, state: dict[str, Tensor]) -> None:
        """Replace the sums and counts by those of :meth:`state_dict`. Every entry must be finite
        and >= 0 (every metric is), and the two counts integers: ValueError naming the entry."""
        value = state.get("state") if isinstance(state, dict) else None
        if not isinstance(value, Tensor) or value.shape != self.state.shape or skip_values(value):
            raise ValueError(f"state: expected {{'state': tensor of shape {tuple(self.state.shape)}}}, "
                             f"got {state!r:.80}")
        loaded = value.detach().to(dtype=torch.float64, device=self.state.device).clone()
        n = len(_MAPS)
        names = ([f"the pixel sum of {k}" for k in _MAPS] + ["the count n_pixels"]
                 + [f"the per-image sum of {k}" for k in _MAPS] + ["the count n_images"])
        for i, x in enumerate(loaded.tolist()):
            count = i in (n, 2 * n + 1)
            if not (math.isfinite(x) and x >= 0 and (not count or x == int(x))):
                raise ValueError(f"state['state'][{i}] ({names[i]}): expected a finite "
                                 f"{'integer' if count else 'number'} >= 0, got {x!r}")
        self.state = loaded

    def __repr__(self) -> str:
        return f"FlowMetricAccumulator(n_pixels={self.n_pixels}, n_images={self.n_images})"
