"""Road motion over a clip: the camera's attitude over the road calibrated without poses, the motion
carried from pair to pair, and the attitude track smoothed.

A clip of N + 1 frames gives N pairs. Each pair's road motion is fitted to its two images
(:func:`~fsof_torch.estimation.image_fit.fit_image`, the ``"plane"`` model), started from the
previous pair's motion and a constant-velocity prediction besides fit_image's own starts (zero
motion, straight ahead), and tied to the previous pair's motion by a loose prior where that pair
succeeded and moved (a fit that fails under it, or lies more than 3 σ from it, is fitted again
without it: a dropped frame, a repeated one). Then:

1. **Calibration.** The camera's mounting (its roll and pitch over the road) is the robust mean of
   the per-pair attitudes, each weighted by its precision (the inverse of its posterior variance:
   a pair that moves little shows the attitude less; of fewer than five, their median): the
   body's pitching and rolling averages out over a clip. With poses
   (metric translations), the camera height follows as well (only d / h is observable from
   images), and the translations returned are in metres at that height. Failed fits calibrate
   nothing, nor do pairs that do not move (a stop: without a translation the road's normal does
   not enter the homography, and the fit's attitude is its prior's), nor pairs whose images fix
   the attitude less well than the prior does (a posterior variance above half the prior's: a
   vehicle creeping by millimetres, whose fit's attitude lies between the prior's and the
   truth): where no pair's fit succeeds and shows the attitude, the input camera's mounting
   stays and the second pass,
   which would only repeat the first, is skipped (with ``keep_fits`` the first runs again to keep
   its fits).
2. **Smoothing.** The camera's attitude over the road at frame k+1 is its attitude at frame k
   plus the body's pitch and roll change between them (on a flat road, to first order). Each pair
   measures both; a weighted least-squares track over the clip makes them consistent, with the
   changes (well measured) tying the noisy absolute attitudes together. A pair that does not
   move measures its change (a rotation) but not its attitude; a failed pair neither (its change
   is taken as none, loosely: it links the frames on either side).
3. **Second pass.** Every pair is fitted again, started at the smoothed track and tied to it by a
   prior: its attitude by the track's own uncertainty there, its attitude change by a tenth of
   ``body_rotation_deg`` (the changes' uncertainty in the smoothing); its translation and
   yaw are started from (and, where that pair succeeded and moved, loosely tied to) the previous
   pair's motion.

Frames are (B=1 per frame) images (3 or 1, H, W) on 0..``data_range`` (255 unless given, as
fit_image's option); masks (1, H, W) bool (one for the clip, or one per pair). Not differentiable.
The results (the fits, the parameters, ``success``) are on the frames' device, any poses given
elsewhere included.

**Memory.** The frames and masks are read in order, one pair at a time, and each frame once per
pass, so a lazy sequence that loads frame k on ``frames[k]`` keeps a clip of any length in the
memory of a few frames; between pairs only each pair's parameters and success are kept (and, with
``keep_fits``, the final pass's full :class:`~fsof_torch.estimation.flow_fit.RoadFit`).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, replace
from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor

from .._check import (check_bool, check_data_range, check_float_tensor, check_has_values, check_image_range, check_names,
                      option_error, scalar, summary_repr)
from ..geometry.camera import Camera
from ..geometry.egomotion import as_pose_4x4, check_pose_steps
from ..geometry.road_models import RoadModel, get_road_model
from .flow_fit import RoadFit, fixed_parameters
from .image_fit import DEG, calibration_prior, check_image_fit_options, fit_image
from .image_options import check_bounds
from .initial import planar_start

__all__ = ["SequenceFit", "fit_sequence", "smooth_attitude"]


@dataclass(eq=False, repr=False)
class SequenceFit:
    """The road motion of a clip (compared by identity, as a :class:`Camera` is).

    Attributes:
        fits: one :class:`~fsof_torch.estimation.flow_fit.RoadFit` per pair (the second pass,
            with the smoothed attitude, or the first with ``passes=1``); empty with
            ``keep_fits=False`` (each holds a full-size flow and two masks: 4.7 MB a pair at
            375×1242 in float32, 8.4 MB with a float64 camera).
        params: ``{name: (N,)}`` the pairs' parameters (float64; translations in metres at
            ``camera``'s height, like the fits').
        mounting: ``{"roll": float, "pitch": float}`` the calibrated attitude (radians), and
            ``"height"`` (metres) when poses gave the scale.
        camera: the input camera with the calibrated roll, pitch (and height).
        first_pass: ``{name: (N,)}`` the per-pair parameters before calibration (fitted with the
            input camera: translations at its height), for reference.
        success: (N,) bool, whether each pair's fit succeeded (of the same pass as ``params``).
        calibrated_from: how many first-pass fits the mounting comes from (those that succeeded,
            move, a fitted translation above 1 mm at the input camera's height, and whose images
            fixed the roll and pitch at least as well as the prior: a posterior variance at most
            half the prior's); 0 where there are none: the mounting is then the input camera's,
            and the second pass is skipped.
    """

    fits: list[RoadFit]
    params: dict[str, Tensor]
    mounting: dict[str, float]
    camera: Camera
    first_pass: dict[str, Tensor]
    success: Tensor
    calibrated_from: int
    __repr__ = summary_repr


def smooth_attitude(attitude: Tensor, change: Tensor, attitude_sigma: Tensor | float,
                    change_sigma: Tensor | float) -> tuple[Tensor, Tensor]:
    """A consistent attitude track (N + 1,) from per-pair measurements of the attitude at the
    pair's first frame (N,) and of its change to the next frame (N,), by weighted least squares:
    minimise Σ ((a_k − attitude_k) / σ_a)² + Σ ((a_{k+1} − a_k − change_k) / σ_c)². The last
    frame's attitude rests on the changes alone. Measurements with infinite σ do not count (at least
    one attitude must, its 1 / σ² above 0 in float64: else a ValueError, the track being fixed only
    up to a constant). Frames that no chain of counting changes ties to a counting attitude (the
    last one where the last change's σ is infinite) are not placed: a tiny ridge keeps the system
    solvable, and their standard deviations come back about 1e6 rad (1e6 / √n for n such frames
    that changes tie together, their mean 0; a lone frame is 0), whatever their measurements say.

    The normal equations are tridiagonal (each term ties at most two neighbouring frames), so the
    track and the diagonal of its covariance take O(N) time and memory: an LDLᵀ factorisation,
    forward and back substitution, and the covariance's diagonal by the backward recursion
    Σ_kk = 1 / D_k + l_k² Σ_{k+1,k+1}. None of them cancels, however much more the changes weigh
    than the attitudes: the pivots D_k are sums of positive terms, and the track is solved as the
    changes' running sum plus a smooth part (whose right-hand side holds the attitudes' residuals
    from that sum, not 1 / σ_c² · change).

    Returns the track (N + 1,) and its standard deviations (N + 1,) (float64)."""
    for name, x in (("attitude", attitude), ("change", change)):
        check_float_tensor(x, name)
        check_has_values(x, name, "for the track (it is solved on the host)")
        if x.dim() != 1:
            raise ValueError(f"{name}: expected a 1-D tensor (one value per pair), got shape {tuple(x.shape)}")
    N = attitude.shape[0]
    if N == 0:  # (the track of one frame that nothing measures: it came back 0 ± 1e6 rad)
        raise ValueError("attitude: expected at least one value (one per pair), got none")
    if change.shape[0] != N:
        raise ValueError(f"change: expected {N} values (attitude's), got {change.shape[0]}")
    dt = torch.float64
    sigmas = []
    for name, given in (("attitude_sigma", attitude_sigma), ("change_sigma", change_sigma)):
        if isinstance(given, bool) or not isinstance(given, (Tensor, numbers.Real)):
            raise TypeError(f"{name}: expected a number or a tensor of {N} values, got {type(given).__name__}")
        check_has_values(given, name, "for the track's weights")
        sigma = torch.as_tensor(given, dtype=dt, device="cpu")  # (the track is solved on the host)
        if sigma.dim() > 1 or sigma.numel() not in (1, N):
            raise ValueError(f"{name}: expected a number or a tensor of {N} values, got shape {tuple(sigma.shape)}")
        if not bool((sigma > 0).all()):  # (NaN fails too; inf is allowed: that measurement does not count)
            got = _where_bad(sigma, ~(sigma > 0)) if sigma.dim() else repr(sigma.item())
            raise ValueError(f"{name}: expected values > 0 (inf: the measurement does not count), got {got}")
        sigmas.append(sigma.expand(N))
    wa, wc = (1.0 / s.square() for s in sigmas)
    for w, sigma, name in ((wa, sigmas[0], "attitude_sigma"), (wc, sigmas[1], "change_sigma")):
        if not bool(torch.isfinite(w).all()):  # (1 / σ² beyond float64's range: the track came back NaN)
            raise ValueError(f"{name}: expected values whose 1 / σ² is finite in float64 (about 1.3e-154 and "
                             f"above), got {sigma.min().item()!r}")
    if not bool((wa > 0).any()):  # (the changes alone fix the track up to a constant: singular)
        raise ValueError(f"attitude_sigma: expected at least one value whose 1 / σ² is > 0 in float64 (an attitude "
                         f"that counts: the changes alone fix the track only up to a constant), got smallest "
                         f"{sigmas[0].min().item()!r}")
    att, chg = attitude.to(dt).cpu(), change.to(dt).cpu()
    # a measurement that does not count contributes nothing, whatever its value (also NaN)
    for w, x, name in ((wa, att, "attitude"), (wc, chg, "change")):
        if not bool(torch.isfinite(x[w > 0]).all()):
            raise ValueError(f"{name}: expected finite values where the sigma is finite, got "
                             f"{_where_bad(x, ~torch.isfinite(x) & (w > 0))}")
    att, chg = torch.where(wa > 0, att, 0.0), torch.where(wc > 0, chg, 0.0)
    # the track as the changes' sum p (p_0 = 0, p_{k+1} = p_k + c_k) plus a smooth part z, a = p + z: z
    # minimises Σ wa_k (z_k + p_k − attitude_k)² + Σ wc_k (z_{k+1} − z_k)² (+ a tiny ridge on a, which keeps
    # a frame no measurement reaches, all its σ infinite, solvable). Its matrix: the diagonal wa (none at
    # the last frame) and the ridge, plus the changes' Laplacian (each wc_k adds the 2 × 2 block
    # [[1, −1], [−1, 1]] wc_k), the off-diagonal −wc (N,); its right-hand side holds no wc · c term.
    ridge = 1e-12
    w_a, w_c, measured = wa.tolist() + [0.0], wc.tolist(), att.tolist() + [0.0]
    p = [0.0]
    for c in chg.tolist():
        p.append(p[-1] + c)
    rhs = [w_a[k] * (measured[k] - p[k]) - ridge * p[k] for k in range(N + 1)]
    # A = L D Lᵀ, L unit lower bidiagonal with L[k+1, k] = l_k = −wc_k / D_k; forward substitution
    # alongside. D_k = wc_k + s_k, s_k (what frame k holds beyond its tie to the next) a sum of positive
    # terms: s_{k+1} = wa_{k+1} + ridge + wc_k s_k / (wc_k + s_k). (The textbook D_{k+1} = A_{k+1,k+1} −
    # wc_k² / D_k, and a right-hand side of wc · c terms, cancel: with σ_a 1° and σ_c 1e-8 rad the track
    # was about 1e-6 rad off, with σ_c 1e-10 rad D came out 0, a ZeroDivisionError.)
    s = w_a[0] + ridge
    D, l, y = [], [], [rhs[0]]
    for k in range(N):
        D.append(w_c[k] + s)
        l.append(-w_c[k] / D[k])
        y.append(rhs[k + 1] - l[k] * y[k])
        s = w_a[k + 1] + ridge + (s / (1.0 + s / w_c[k]) if w_c[k] > 0 else 0.0)
    D.append(s)
    z, var = [0.0] * (N + 1), [0.0] * (N + 1)
    z[N], var[N] = y[N] / D[N], 1.0 / D[N]
    for k in range(N - 1, -1, -1):
        z[k] = y[k] / D[k] - l[k] * z[k + 1]
        var[k] = 1.0 / D[k] + l[k] * l[k] * var[k + 1]
    x = [p_k + z_k for p_k, z_k in zip(p, z)]
    device = attitude.device
    return torch.tensor(x, dtype=dt, device=device), torch.tensor(var, dtype=dt, device=device).sqrt()


def _where_bad(x: Tensor, bad: Tensor) -> str:
    """The values of ``x`` (1-D) where ``bad``, with their indices, the first three of them: a
    message that quotes a clip's every value runs to megabytes, and a tensor's repr elides the
    middle, where the bad one may be."""
    index = bad.nonzero().flatten().tolist()
    more = f" and {len(index) - 3} more" if len(index) > 3 else ""
    return ", ".join(f"{x[i].item()!r} at [{i}]" for i in index[:3]) + more


#: a pair whose fitted translation (at the input camera's height) is at most this, in metres, does
#: not move: it measures neither the camera's attitude over the road (the road's normal enters the
#: homography only through the translation) nor the scale of poses. Still frames of a real clip
#: (a frame repeated, with sensor noise) fit to a few 1e-4 m.
_STILL_M = 1e-3

#: the fewest values of which :func:`_robust_mean` leaves any out by their deviation. Of fewer, the
#: median absolute deviation is set by the nearer of the two outer values (of 3 it is its deviation,
#: of 4 the mean of it and the middle two's half-gap), which then judges the other: a good pair was
#: dropped where it lay 4.4 (of 4: 2.2) times as far off, as the body's pitching and rolling can put
#: it. Of fewer the median stands in, which one far value (a fit that succeeded at a wrong attitude)
#: cannot move either; from 5 on, the inner values can set the deviation.
_MIN_REJECT = 5

#: the most the camera height from poses may differ from the input camera's, as a factor either way.
#: The images give d / h, so poses in other units than metres scale the height by the unit: 100 (cm),
#: 1000 (mm), 1 / 1000 (km). A calibrated height is never off by a factor of 10, nor is a guessed one
#: (road vehicles carry their cameras about 0.5 m to 4 m over the road); a tighter one, 5, would
#: refuse a low robot's camera (0.3 m) left at a car's nominal 1.65 m.
_MAX_HEIGHT_FACTOR = 10.0


def _robust_mean(x: Tensor, ok: Tensor, variance: Tensor | None = None) -> float:
    """The mean of the values within 3 median absolute deviations of their median, weighted by
    their inverse ``variance`` where given (positive and finite for all of them; else equally);
    below ``_MIN_REJECT`` values their median (success only: ``ok`` has at least one)."""
    v = x[ok]
    if v.numel() < _MIN_REJECT:
        return float(v.quantile(0.5))
    # (the median of an even count is the mean of the middle two: torch's ``median`` takes the lower,
    # which with two values made the deviation 0 and kept only the lower one)
    med = v.quantile(0.5)
    mad = (v - med).abs().quantile(0.5).clamp_min(1e-9)
    keep = (v - med).abs() <= 3 * 1.4826 * mad
    var = None if variance is None else variance[ok][keep].double()
    if var is None or not bool(((var > 0) & torch.isfinite(var)).all()):  # (a held angle: variance 0)
        return float(v[keep].mean())
    w = 1.0 / var
    return float((w * v[keep]).sum() / w.sum())


@dataclass
class _PairRecord:
    """What a pass keeps of a pair's fit: its parameters ({name: (1,)}), whether it succeeded, the
    posterior variances of its roll and pitch ({name: float}), and whether its images fixed them
    at least as well as its prior did."""

    params: dict[str, Tensor]
    success: bool
    variance: dict[str, float] | None = None
    attitude_seen: bool = True


def _attitude(fit: RoadFit, prior: dict[str, tuple[Any, Any]]) -> tuple[dict[str, float], bool]:
    """The posterior variances of the fit's roll and pitch (0 where held), and whether the images
    fixed them at least as well as their prior did: a variance at most half the prior's (the
    images' information at least the prior's; a held angle, or one without a prior, passes)."""
    names = get_road_model(fit.model).params  # (the covariance's order)
    variance = {n: float(fit.covariance[0, names.index(n), names.index(n)]) for n in ("roll", "pitch")}
    seen = all(variance[n] <= 0.5 * float(torch.as_tensor(prior[n][1], device="cpu").reshape(-1)[0]) ** 2
               for n in ("roll", "pitch") if n in prior)
    return variance, seen


def _stack(records: Sequence[_PairRecord]) -> dict[str, Tensor]:
    return {k: torch.cat([r.params[k].double().reshape(-1) for r in records]) for k in records[0].params}


def _item(x: object, name: str, what: str, channels: tuple[int, ...], size: tuple[int, int] | None = None,
          device: torch.device | None = None) -> Tensor:
    """One frame, mask or flow of a clip as (1, C, H, W), checked: C in ``channels``, (H, W) the
    clip's ``size`` and on ``device`` (``frames[0]``'s) where known (items are read lazily, one by
    one), with values (not on the meta device)."""
    if not isinstance(x, Tensor):
        raise TypeError(f"{name}: expected a tensor ({what}), got {type(x).__name__}")
    y = x.unsqueeze(0) if x.dim() == 3 else x
    if (y.dim() != 4 or y.shape[0] != 1 or y.shape[1] not in channels or min(y.shape[-2:]) < 1
            or (size is not None and tuple(y.shape[-2:]) != size)):
        c = "C" if len(channels) > 1 else str(channels[0])
        hw = "H, W" if size is None else f"{size[0]}, {size[1]}"
        # (the channels a C stands for: a 4-channel RGBA frame, or an (H, W, 3) one, has the shape (C, H, W))
        among = f" with C {' or '.join(map(str, channels))}" if len(channels) > 1 else ""
        raise ValueError(f"{name}: expected shape ({c}, {hw}) or (1, {c}, {hw}){among} ({what}), got {tuple(x.shape)}")
    # (named here by its index: fit_image named it image1, image2, mask or flow, whichever pair it came in)
    check_has_values(y, name, "to fit (a fit is iterative and data dependent)")
    if device is not None and y.device != device:
        raise ValueError(f"{name}: expected the device of frames[0] ({device}), got {y.device}")
    return y


def _frame(x: object, name: str, data_range: float, channels: tuple[int, ...],
           size: tuple[int, int] | None = None, device: torch.device | None = None) -> Tensor:
    """One frame of a clip (:func:`_item`): a float image on 0..``data_range``, of the clip's
    channels and size, named by its index where it is not."""
    what = "an image" if size is None else f"an image of the clip's {channels[0]} channel(s) and size"
    y = _item(check_float_tensor(x, name) if isinstance(x, Tensor) else x, name, what, channels, size, device)
    if min(y.shape[-2:]) < 2:  # (fit_image's least, which it named image1: the first frame, named here)
        raise ValueError(f"{name}: expected an image of at least 2x2 pixels (the image fit's), got shape "
                         f"{tuple(x.shape)}")
    check_image_range(y, name, data_range)
    return y


@torch.no_grad()
def fit_sequence(frames: Sequence[Tensor], mask: Tensor | Sequence[Tensor], camera: Camera, *,
                 poses: Tensor | None = None, flows: Sequence[Tensor] | None = None,
                 passes: int = 2, attitude_deg: float = 1.0, body_rotation_deg: float = 0.3,
                 keep_fits: bool = True, progress: bool = False, **options: Any) -> SequenceFit:
    """Fit the ``"plane"`` road motion of every pair of a clip, calibrating the camera's attitude
    over the road without poses (see the module docstring).

    Args:
        frames: N + 1 images, each (C, H, W) or (1, C, H, W) of at least 2x2 pixels, on
            0..``data_range`` (an option of fit_image, 255 unless given): any sequence with
            ``len()`` and indexing, e.g. a list or a lazy object that loads frame k on ``frames[k]``.
            Each pass reads every frame once, in order (``frames[0]``, ``frames[1]``, ...), and
            holds at most the two frames of the pair it is fitting. The masks and flows on
            ``frames[0]``'s device, as every frame (else a ValueError names the item,
            ``frames[k]``, ``mask[k]`` or ``flows[k]``).
        mask: the road pixels of every first frame: one (1, H, W) / (1, 1, H, W) bool tensor for the
            clip, or a sequence of N (read like ``frames``: ``mask[k]`` when pair k is fitted).
        camera: intrinsics, height and the nominal roll and pitch (batch 1).
        poses: optional (N + 1, 4, 4) camera-to-world poses in metres: their translations give the
            metric scale, hence the camera height (the images give d / h only). Poses that are not
            rigid transforms (a rotation block, the bottom row 0 0 0 1: a transposed pose has its
            translation there) are a ValueError naming ``poses``. Consecutive poses farther apart
            than a road vehicle travels between two frames (100 m; poses in millimetres) are a
            ValueError naming ``poses`` and the frames, and so is a height more than 10 times the
            camera's, or under a tenth of it (poses in other units).
        flows: optional N predicted flows (2, H, W) or (1, 2, H, W): starts from their planar
            motion (a sequence read like ``frames``).
        passes: 1 (per-pair fits only; with poses, their translations and cameras rescaled to the
            calibrated height) or 2 (fitted again with the calibrated attitude and height).
        attitude_deg: the prior's standard deviation of the per-frame attitude around the
            calibrated mounting (the body's pitching and rolling), degrees; with two passes at most
            about 7.7e155 (the smoothed track weighs each attitude by 1 / σ² in float64: a
            ValueError names it where that is 0).
        body_rotation_deg: the standard deviation of the body's pitch and roll change per frame.
        keep_fits: keep the final pass's :class:`~fsof_torch.estimation.flow_fit.RoadFit` of every
            pair in ``SequenceFit.fits`` (False: ``fits`` is empty and no full-size map outlives
            its pair; the parameters and ``success`` are the same).
        progress: show a progress bar.
        **options: further keyword arguments of :func:`~fsof_torch.estimation.image_fit.fit_image`,
            their values checked before any frame is read. Parameters held by ``fixed`` stay where
            the first pass holds them in both passes: no motion, the input camera's roll and pitch
            (the mounting then calibrated to them), not the smoothed track.

    Returns:
        :class:`SequenceFit`.
    """
    given = {"frames": frames, "mask": mask, **({} if flows is None else {"flows": flows})}
    for name, value in given.items():  # (a mask may also be one tensor for the clip)
        if not (isinstance(value, Tensor) or hasattr(value, "__len__") and hasattr(value, "__getitem__")):
            raise TypeError(f"{name}: expected a sequence of tensors (a list, or an object with len() and "
                            f"indexing), got {type(value).__name__}")
    if isinstance(mask, np.ndarray):  # (not a sequence of N masks: one array read row by row)
        raise TypeError(f"mask: expected a bool tensor (1, H, W) or a sequence of them, got ndarray of shape "
                        f"{mask.shape}")
    if len(frames) < 2:
        raise ValueError(f"frames: expected at least 2 frames, got {len(frames)}")
    passes = scalar(passes, "passes")  # (a 0-d integer tensor as its int)
    if isinstance(passes, bool) or not isinstance(passes, numbers.Integral) or passes not in (1, 2):
        raise option_error(passes, f"passes: expected 1 or 2, got {passes!r}", integer=True)
    passes = int(passes)
    keep_fits, progress = check_bool(keep_fits, "keep_fits"), check_bool(progress, "progress")
    attitude_deg, body_rotation_deg = scalar(attitude_deg, "attitude_deg"), scalar(body_rotation_deg, "body_rotation_deg")
    for name, value in (("attitude_deg", attitude_deg), ("body_rotation_deg", body_rotation_deg)):
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not (0 < value < math.inf):
            raise option_error(value, f"{name}: expected a finite number of degrees > 0 (a standard deviation), "
                                      f"got {value!r}")
    # (the second pass's smoothed track weighs the attitudes by 1 / σ² in float64, 0 where σ² overflows:
    # smooth_attitude refused that after a whole first pass, naming its own attitude_sigma)
    sigma = attitude_deg * DEG
    if passes == 2 and 1.0 / (sigma * sigma) == 0.0:
        raise ValueError(f"attitude_deg: expected a standard deviation whose weight 1 / σ² in radians is above 0 in "
                         f"float64 (below about 7.7e155 degrees: the second pass's attitude track needs attitudes "
                         f"that count), got {attitude_deg!r}")
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera of batch 1, got {type(camera).__name__}")
    if camera.batch_size != 1:
        raise ValueError(f"camera: expected batch 1 (one camera for the clip), got {camera.batch_size}")
    N = len(frames) - 1
    if not isinstance(mask, Tensor) and len(mask) != N:
        raise ValueError(f"mask: expected one mask or {N} (one per pair), got {len(mask)}")

    def mask_of(k: int, size: tuple[int, int], device: torch.device) -> Tensor:
        name = "mask" if isinstance(mask, Tensor) else f"mask[{k}]"
        m = mask if isinstance(mask, Tensor) else mask[k]
        if isinstance(m, Tensor) and m.dim() == 2:
            m = m.unsqueeze(0)
        m = _item(m, name, "the road of the pair's first frame", (1,), size, device)
        if m.dtype != torch.bool:
            raise TypeError(f"{name}: expected a bool tensor, got dtype {m.dtype}")
        return m

    if poses is not None:
        try:  # (a list of tensors of other shapes: torch.stack's RuntimeError, naming nothing)
            if isinstance(poses, (list, tuple)) and all(isinstance(p, Tensor) for p in poses):
                poses = torch.stack(poses) if poses else torch.empty(0, device="cpu")
            poses = poses if isinstance(poses, Tensor) else torch.as_tensor(poses, device="cpu")
        except (TypeError, ValueError, RuntimeError) as err:
            raise TypeError(f"poses: expected a float tensor of shape ({N + 1}, 4, 4) (one per frame), got "
                            f"{type(poses).__name__} ({err})") from None
        if not poses.is_floating_point():
            raise TypeError(f"poses: expected a float tensor of shape ({N + 1}, 4, 4) (one per frame), got dtype "
                            f"{poses.dtype}")
        if poses.shape != (N + 1, 4, 4):
            raise ValueError(f"poses: expected a float tensor of shape ({N + 1}, 4, 4) (one per frame), got "
                             f"{poses.dtype} {tuple(poses.shape)}")
        # (on the meta device the finiteness test was torch's RuntimeError "Tensor.item() cannot be called
        # on meta tensors")
        check_has_values(poses, "poses", "to give the clip's translations their scale")
        if not bool(torch.isfinite(poses).all()):
            raise ValueError("poses: expected finite values, got NaN or inf")
        # (only the translations are used, but a pose that is no rigid transform is no pose: a transposed
        # one, its translation in the bottom row, was "their translations give no scale" after a whole pass,
        # and a scaled or sheared rotation block passed unremarked)
        as_pose_4x4(poses, "poses")
        check_pose_steps(poses, "poses", labels=[f"the pose of frames[{k}]" for k in range(N + 1)])
    if flows is not None and len(flows) != N:
        raise ValueError(f"flows: expected {N} flows (one per pair), got {len(flows)}")
    # (the values too, before any frame is read)
    check_image_fit_options(options, "options", reserved=("init", "starts", "prior"))
    model = get_road_model(options.pop("model", "plane"))
    data_range = check_data_range(options.get("data_range", 255.0))
    if model.name != "plane":
        raise ValueError("model: a clip is fitted with the 'plane' model (its attitude is tracked)")
    # (each pair is a fit of one frame: bounds of batch 1, named before a frame is read, not at the first fit)
    check_bounds(options.get("bounds"), model, 1)
    motion = [n for n in model.params if n not in model.mounting]
    held = fixed_parameters(model, check_names(options.get("fixed"), "fixed"))

    attitude = ("roll", "pitch", "roll_change", "pitch_change")

    def run(cam: Camera, label: str, track: dict[str, tuple[Tensor, Tensor]] | None = None,
            keep: bool = False) -> tuple[list[_PairRecord], list[RoadFit]]:
        from ..io.progress import progress_bar

        records: list[_PairRecord] = []
        fits: list[RoadFit] = []
        image2 = None
        for k in progress_bar(range(N), enabled=progress, desc=f"road motion: {label}", unit="pair"):
            starts: list[dict] = []
            prior = calibration_prior(model, cam, mounting_deg=attitude_deg, body_rotation_deg=body_rotation_deg)
            if records:
                prev = {n: records[-1].params[n] for n in motion}
                starts.append(prev)
                if len(records) > 1:  # constant velocity: the motion changes as it did
                    starts.append({n: 2 * records[-1].params[n] - records[-2].params[n] for n in motion})
                step = torch.stack([prev[n] for n in ("x_d", "y_d", "z_d")]).norm()
                # the previous motion, loosely: a car changes speed gently. Not after a pair that did not
                # move: a frame repeated (a recording's glitch) stands still for one pair and not the
                # next, whose step a prior at 0 ± 5 cm made fail (or biased) where it fits alone
                carried = {}
                if records[-1].success and float(step) > _STILL_M:
                    z = prev["z_d"].abs()
                    carried = dict(x_d=(prev["x_d"], 0.05 + 0.1 * z), z_d=(prev["z_d"], 0.05 + 0.1 * z),
                                   yaw=(prev["yaw"], 1.0 * DEG))
                    prior.update(carried)
            else:
                carried = {}
            # each frame is read once per pass, in order: the last pair's second frame is this one's first
            image1 = image2 if image2 is not None else _frame(frames[k], f"frames[{k}]", data_range, (1, 3))
            size = tuple(image1.shape[-2:])
            image2 = _frame(frames[k + 1], f"frames[{k + 1}]", data_range, (image1.shape[1],), size, image1.device)
            road = mask_of(k, size, image1.device)
            if flows is not None:
                given = flows[k]  # (an integer or bool flow was taken as pixels, truncated)
                given = check_float_tensor(given, f"flows[{k}]") if isinstance(given, Tensor) else given
                flow = _item(given, f"flows[{k}]", "a flow of the frames' size", (2,), size, image1.device)
                starts.append(planar_start(flow.to(torch.float64), road, cam))
            init = None
            if track is not None:  # the attitude and its change: start at the smoothed track, tied to it
                init = {}
                for n in ("roll", "pitch"):
                    value, sigma = track[n]
                    init[n], init[n + "_change"] = value[k:k + 1], value[k + 1:k + 2] - value[k:k + 1]
                    prior[n] = (init[n], sigma[k:k + 1])
                    prior[n + "_change"] = (init[n + "_change"], 0.1 * body_rotation_deg * DEG)
                starts = [{n: v for n, v in st.items() if n not in attitude} for st in starts]
                # a held parameter stays where the first pass held it (the camera's roll or pitch, no
                # change), not at the track: fit_image holds it at init's value
                init = {n: v for n, v in init.items() if n not in held} or None
            prior = {n: v for n, v in prior.items() if n not in held}  # (held: no prior, fit_image refuses it)
            fit = fit_image(image1, image2, road, cam, model=model, init=init, starts=starts, prior=prior,
                            **options)
            carried = {n: v for n, v in carried.items() if n in prior}
            if carried and _contradicted(fit, carried):
                # the images disagree with the carried motion (a dropped frame, a hard brake at a low
                # frame rate) or the fit failed under it: the pair fitted without it, where that succeeds
                alone = fit_image(image1, image2, road, cam, model=model, init=init, starts=starts,
                                  prior={n: v for n, v in prior.items() if n not in carried}, **options)
                if bool(alone.success.all()):
                    fit = alone
            records.append(_PairRecord({n: v.detach() for n, v in fit.params.items()}, bool(fit.success.all()),
                                       *_attitude(fit, prior)))
            if keep:
                fits.append(fit)
            del image1, road, fit  # none outlives its pair: freed before the next pair is read
        return records, fits

    first, fits = run(camera, "first pass", keep=keep_fits and passes == 1)
    raw = _stack(first)
    # (the pairs' bookkeeping on the fits' device, the frames': a CPU tensor beside them was torch's
    # "Expected all tensors to be on the same device" with the frames on a GPU)
    dev = raw["z_d"].device
    ok = torch.tensor([r.success for r in first], device=dev)
    image_steps = torch.stack([raw["x_d"], raw["y_d"], raw["z_d"]], -1).norm(dim=-1)  # at the nominal height
    # a pair that does not move measures no attitude: with t = 0 the road's homography K R K⁻¹ holds no
    # normal, and its fit's roll and pitch are where its prior put them (the input camera's); one
    # that creeps measures it little, its fit's attitude drawn towards the prior's
    moving = ok & (image_steps > _STILL_M)
    attitude_ok = moving & torch.tensor([r.attitude_seen for r in first], device=dev)
    calibrated_from = int(attitude_ok.sum())
    if calibrated_from:
        # (weighted by each pair's precision: a pair that moves little shows the attitude less)
        roll0, pitch0 = (_robust_mean(raw[n], attitude_ok, torch.tensor([r.variance[n] for r in first], device=dev))
                         for n in ("roll", "pitch"))
    else:  # failed or still fits calibrate nothing: the input camera's mounting stays
        roll0, pitch0 = float(camera.roll[0]), float(camera.pitch[0])
    mounting = {"roll": roll0, "pitch": pitch0}
    cam = camera.replace(roll=roll0, pitch=pitch0)
    if poses is not None:
        P = torch.as_tensor(poses, dtype=torch.float64, device=dev)
        steps = (P[1:N + 1, :3, 3] - P[:N, :3, 3]).norm(dim=-1)
        use = moving  # (the pairs that succeeded and move: a creeping one's translation gives a scale too)
        if bool(use.any()):
            # metric step = (d / h) h: h = h_nominal · median(metric / image-derived) over the pairs whose
            # poses move. A pair whose poses stand still (at most _STILL_M) gives no scale: a stop's frames
            # with sensor noise fit a few mm (0.4 to 11 mm on synthetic stops with KITTI's noise), above
            # _STILL_M, and counted as ratios 0 they took the median to 0 or drew it down. The poses are
            # refused where the pairs in which they stand still move in the images at least half as far
            # as the others (poses still in one of two pairs that move alike are refused either way).
            still = steps[use] <= _STILL_M
            ratios = steps[use][~still] / image_steps[use][~still]
            height = float(camera.height[0]) * float(ratios.quantile(0.5)) if bool((~still).any()) else 0.0
            against, along = (float(image_steps[use][s].sum()) for s in (still, ~still))
            if not (math.isfinite(height) and height > 0) or along <= 2 * against:
                raise ValueError(f"poses: their translations give no scale (camera height {height:g} m): the "
                                 f"poses do not move where the images do (they stand still in {int(still.sum())} "
                                 f"of the {int(still.numel())} pairs whose images move, which move {against:.3g} "
                                 f"m in the images at the camera's height, the others {along:.3g} m)")
            nominal = float(camera.height[0])
            if not 1 / _MAX_HEIGHT_FACTOR <= height / nominal <= _MAX_HEIGHT_FACTOR:
                raise ValueError(f"poses: their translations give a camera height of {height:g} m, "
                                 f"{height / nominal:.3g} times the camera's {nominal:g} m (more than "
                                 f"{_MAX_HEIGHT_FACTOR:g} times either way): expected camera-to-world poses of "
                                 f"these frames in metres (not millimetres or centimetres)")
            mounting["height"] = height
            cam = cam.replace(height=height)
    records = first
    if passes == 2 and calibrated_from:
        track = _track(raw, ok, attitude_ok, attitude_deg, body_rotation_deg)
        records, fits = run(cam, "smoothed attitude", track, keep=keep_fits)
    else:
        if passes == 2 and keep_fits:  # nothing calibrated: the first pass again, for its fits
            # (with the input camera, as the first pass: at the poses' height the priors in metres
            # weighed otherwise, and the parameters differed from those of keep_fits=False)
            records, fits = run(camera, "first pass, kept", keep=True)
        if "height" in mounting:  # the first pass's translations, in the metric height's units
            ratio = mounting["height"] / float(camera.height[0])
            records = [_PairRecord(_metric(r.params, model, ratio), r.success) for r in records]
            fits = [_metric_fit(fit, model, ratio, cam.height) for fit in fits]
    success = torch.tensor([r.success for r in records], device=dev)
    # (a detached copy: results are detached, and not the caller's camera's storage)
    cam = Camera._checked(*(t.detach().clone() for t in (cam.K, cam.height, cam.roll, cam.pitch)))
    return SequenceFit(fits, _stack(records), mounting, cam, raw, success, calibrated_from)


def _contradicted(fit: RoadFit, carried: dict[str, tuple[Tensor, Any]]) -> bool:
    """Whether ``fit`` failed, or lies more than 3 standard deviations from the motion ``carried`` from
    the previous pair as a prior ({name: (mean, σ)}) in any of its parameters: a prior pulls the fit
    towards itself, so a fit that still lies that far is one the images contradict it in."""
    if not bool(fit.success.all()):
        return True
    for name, (mean, sigma) in carried.items():
        value = fit.params[name].double().reshape(-1)
        off = (value - torch.as_tensor(mean, dtype=torch.float64, device=value.device).reshape(-1)).abs()
        if bool((off > 3 * torch.as_tensor(sigma, dtype=torch.float64, device=value.device).reshape(-1)).any()):
            return True
    return False


def _metric(params: dict[str, Tensor], model: RoadModel, ratio: float) -> dict[str, Tensor]:
    """``params`` with the translations (metres) scaled by ``ratio`` (the images fix d / h only:
    at a camera height ``ratio`` times the one fitted at, the same motion)."""
    metres = {n for n, unit in zip(model.params, model.units) if unit == "m"}
    return {n: v * ratio if n in metres else v for n, v in params.items()}


def _metric_fit(fit: RoadFit, model: RoadModel, ratio: float, height: Tensor) -> RoadFit:
    """:func:`_metric` of a fit: its parameters, their covariance, and its camera at ``height``
    (the map and the flow stay the same)."""
    cov = fit.covariance
    if cov is not None:
        scale = torch.tensor([ratio if unit == "m" else 1.0 for unit in model.units], dtype=cov.dtype, device=cov.device)
        cov = cov * scale.unsqueeze(-1) * scale
    camera = fit.camera.replace(height=height.to(fit.camera.height))
    return replace(fit, params=_metric(fit.params, model, ratio), covariance=cov, camera=camera)


def _track(params: dict[str, Tensor], ok: Tensor, attitude_ok: Tensor, attitude_deg: float,
           body_rotation_deg: float) -> dict[str, tuple[Tensor, Tensor]]:
    """Smoothed roll and pitch tracks (N + 1,) with their standard deviations; failed pairs do
    not count, and the attitudes only of the pairs in ``attitude_ok`` (those that move; a still
    pair's rotation, its attitude change, is measured all the same). A failed pair's change is
    taken as none, loosely (10 × ``body_rotation_deg``): it only links the frames on either side."""
    # (in float64 from the start: a number made a float32 tensor first, and a σ beyond float32's range
    # was torch's RuntimeError "value cannot be converted to type float without overflow")
    f64 = dict(dtype=torch.float64, device=ok.device)
    sa = torch.where(attitude_ok, torch.tensor(attitude_deg * DEG, **f64), math.inf)
    # the changes are measured far better than the attitudes; a failed pair's change says nothing: its
    # fitted value (anything within the bounds, 5°) moved the whole track: 5° in a clip of 6 pairs moved
    # it by -0.17° before that pair and +0.25° after; the body's change is centred on none
    sc = torch.where(ok, torch.tensor(0.1 * body_rotation_deg * DEG, **f64), 10 * body_rotation_deg * DEG)
    return {n: smooth_attitude(params[n], torch.where(ok, params[n + "_change"], 0.0), sa, sc)
            for n in ("roll", "pitch")}
